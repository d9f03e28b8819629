"""The scene files (``*.toml``). Installed as the package data ``ti_dk.scenes`` (pyproject.toml maps
this folder there), where :mod:`ti_dk.scene.schema` finds them through :mod:`importlib.resources`."""
