"""Whether the tool is in the cut: each source's reading (sources.py) and the one cut state the
chatter analyzer publishes and every other part of the daemon reads (state.py).  docs/chatter.md."""
