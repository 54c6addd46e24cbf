"""lathed: monitoring and control daemon for CNC lathes and their neighbours."""
from lathed.hookspecs import hookimpl

__version__ = "0.1.0"
__all__ = ["hookimpl", "__version__"]
