"""lathed's built-in plugins, installed as the package ``lathed_plugins``
(pyproject.toml maps this folder to that name)."""
if __name__ != "lathed_plugins":
    # Imported by its folder name (from a checkout's directory): a second copy of every
    # plugin module, with its own classes and state, beside lathed_plugins' own.
    raise ImportError(f"import lathed_plugins, not {__name__}: this folder installs as lathed_plugins")
