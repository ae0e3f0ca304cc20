"""Built-in artclass plugins (installed as ``artclass_plugins``).

Each submodule is an entry point of the ``artclass`` group in pyproject.toml, registered exactly as a
third-party plugin would be.
"""
