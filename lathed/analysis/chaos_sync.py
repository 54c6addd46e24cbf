"""Moved to lathed.analysis.chatter.chaos_sync and .eye: these names are kept here for code
written against the old module."""
from lathed.analysis.chatter.chaos_sync import ChaosSyncDetector  # noqa: F401
from lathed.analysis.chatter.eye import (  # noqa: F401
    eye_features, eye_of_difference, eye_radius, lorenz_features)
