"""Chatter detection: the detectors, their windows and rules, the paper's chaos eye, and the
verdict without a reference.  How it works and its options: docs/chatter.md."""
