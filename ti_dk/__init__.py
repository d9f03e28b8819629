"""ti_dk: the Dean–Kawasaki SPDE and Brownian particles in Taichi (Kim, Bell, Garcia et al. hybrid).

Importing ti_dk never starts Taichi; :func:`run` does (CPU unless told), or call :func:`init`.
"""
__version__ = "0.1.0"

from .config import ConfigError, Scene, available_scenes, load_scene  # noqa: E402
from .sim import Result, SimulationError, init, run  # noqa: E402

__all__ = ["ConfigError", "Result", "Scene", "SimulationError", "available_scenes", "init", "load_scene", "run"]
