"""Moved to lathed.analysis.chatter (registry, detectors, base, windows, spectrum): these names
are kept here for code written against the old module."""
from lathed.analysis.chatter.base import RevolutionDetector  # noqa: F401
from lathed.analysis.chatter.detectors import (  # noqa: F401
    SpectralRatioDetector, SyncCusumDetector, SyncResidualDetector)
from lathed.analysis.chatter.registry import (  # noqa: F401
    DEFAULT_DETECTOR, DETECTORS, describe_params, make_detector)
from lathed.analysis.chatter.spectrum import fast_len, median_abs, spectral_peak_hz  # noqa: F401
from lathed.analysis.chatter.windows import BASE_PARAMS, JudgedIndex, Window  # noqa: F401
