"""ti_dk: the Dean–Kawasaki SPDE and Brownian particles in Taichi with the AMAR particle hybrid of
Djurdjevac, Almgren and Bell.

Importing ti_dk never starts Taichi; :func:`run` does (CPU unless told), or call :func:`init`.
"""
import os
import sys

if any(f" -m ti_dk.{m} " in f" {' '.join(getattr(sys, 'orig_argv', []))} " for m in ("scene", "tradeoff")):
    # the command lines (python -m ti_dk.scene, ti_dk.tradeoff): their stop-signal handlers go in
    # before the seconds of imports below
    from .control.signals import catch_early

    catch_early()

# Taichi prints a "[Taichi] version ..." banner when imported unless this is false; this runs before
# any ti_dk module imports taichi, so the banner is off for every entry point.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")

from .scene.load import available_scenes, load_scene  # noqa: E402
from .core.errors import ConfigError, OutputError, SimulationError  # noqa: E402
from .scene.schema import Scene  # noqa: E402
from .output.files import package_version  # noqa: E402
from .control.runtime import Result, init  # noqa: E402
from .control.controller import run  # noqa: E402
from .control.registry import make_solver  # noqa: E402
from .control.tradeoff import tradeoff  # noqa: E402  (python -m ti_dk.tradeoff is the module ti_dk/tradeoff.py)
from .output.series import crossing_rate  # noqa: E402

__version__ = package_version()  # from pyproject.toml, through the installed metadata

__all__ = ["ConfigError", "OutputError", "Result", "Scene", "SimulationError", "available_scenes", "crossing_rate",
           "init", "load_scene", "make_solver", "run", "tradeoff"]
