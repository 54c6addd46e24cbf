"""Moved to lathed.analysis.cut.sources (and the sliding quantile to lathed.analysis.quantile):
these names are kept here for code written against the old module."""
from lathed.analysis.cut.sources import (  # noqa: F401
    SOURCES, FeedStop, LoadCutDetector, VibrationCutDetector)
from lathed.analysis.quantile import SlidingQuantile  # noqa: F401
