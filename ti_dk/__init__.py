"""ti_dk: the Dean–Kawasaki SPDE and Brownian particles in Taichi (Kim, Bell, Garcia et al. hybrid).

Importing ti_dk never starts Taichi; :func:`run` does (CPU unless told), or call :func:`init`.
"""
from .config import ConfigError, Scene, available_scenes, load_scene
from .io import package_version
from .runtime import Result, SimulationError, init
from .sim import run

__version__ = package_version()  # from pyproject.toml, through the installed metadata

__all__ = ["ConfigError", "Result", "Scene", "SimulationError", "available_scenes", "init", "load_scene", "run"]
