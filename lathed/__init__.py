"""lathed: monitoring and control daemon for CNC lathes and their neighbours."""

__version__ = "0.1.0"
__all__ = ["hookimpl", "__version__"]


def __getattr__(name: str):
    # pluggy's marker on first use (`from lathed import hookimpl` in a plugin): lathectl, started
    # hundreds of times by the suite, registers no plugins and need not import pluggy
    if name == "hookimpl":
        from lathed.hookspecs import hookimpl
        return hookimpl
    raise AttributeError(f"module 'lathed' has no attribute {name!r}")
