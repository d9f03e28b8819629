"""A scene's ``[observables]``: named regions given as conditions in x, y, z, and the cells each one counts.

::

    [observables]
    left = "x < 0.5"
    core = "(x - 0.5)**2 + (y - 0.5)**2 < 0.1**2 and not y > 0.6"

A condition is parsed by the scene's safe formula code (:func:`ti_dk.core.expr.parse` with
``logic=True``: numbers, x y z, the formula functions, ``< <= > >=``, ``and or not``). A region
holds the cells whose *centre* satisfies it; its observable is the particle count of those cells
per member, ``Σ_cells q V_c``: the region's integrated density for fv and gaussian, its particles
for the particle method, and for the hybrid the total it reports (SPDE content plus particles).
"""
from __future__ import annotations

import re
from typing import Any

import numpy as np

from ..core.errors import ConfigError, ExprError
from ..core.expr import VARIABLES, axes_used, numpy_value, parse, truth

NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}")  # an observable's name: an identifier
SERIES = ("time", "mass", "negative_cells", "particles", "region_cells")  # a run's own per-member series


def read(value: Any, cells: tuple[int, ...], lengths: tuple[float, ...]) -> tuple[tuple[str, str], ...]:
    """The ``(name, condition)`` pairs of an ``[observables]`` table (a TOML table, or such pairs from
    Python), each condition parsed for this grid and selecting at least one cell; a one-line
    :class:`ConfigError` saying what to change otherwise."""
    if isinstance(value, dict):
        pairs = list(value.items())
    elif isinstance(value, (list, tuple)) and all(isinstance(p, (list, tuple)) and len(p) == 2 for p in value):
        pairs = [tuple(p) for p in value]
    else:
        raise ConfigError(f"observables = {value!r}: give a table [observables] of name = \"condition in x, y, z\"")
    out = []
    for name, text in pairs:
        if not isinstance(name, str) or not NAME_RE.fullmatch(name) or name in SERIES:
            why = "is taken by the run's own series" if name in SERIES else "is not a plain name"
            raise ConfigError(f"[observables] {name!r} {why}: name it with letters, digits and '_' (not "
                              f"{', '.join(SERIES)})")
        try:
            if not mask(text, cells, lengths).any():
                raise ExprError("holds no cell centre of the grid: widen it (a cell counts when its centre is inside)")
        except ExprError as exc:
            raise ConfigError(f"[observables] {name} = {text!r}: {exc}") from None
        out.append((name, text.strip()))
    return tuple(out)


def keys(value: Any, grid) -> dict[str, tuple]:
    """The ``[stats]`` field ``observables`` of a scene's ``observables`` value (None: absent) on ``grid``."""
    return {} if value is None else {"observables": read(value, grid.cells, grid.lengths)}


def mask(text: str, cells: tuple[int, ...], lengths: tuple[float, ...]) -> np.ndarray:
    """Booleans ``(*cells)``: the cells whose centre satisfies condition ``text``."""
    tree = parse(text, logic=True)
    dim = len(cells)
    extra = sorted(a for a in axes_used(tree) if a >= dim)
    if extra:
        raise ExprError(f"uses {VARIABLES[extra[0]]} but the grid is {dim}D: use {', '.join(VARIABLES[:dim])}")
    centres = np.meshgrid(*((np.arange(n) + 0.5) * L / n for n, L in zip(cells, lengths)), indexing="ij", sparse=True)
    return np.broadcast_to(truth(numpy_value(tree, tuple(centres))), cells).copy()


def masks(scene) -> dict[str, np.ndarray]:
    """Each observable's cells, by name (``scene.stats.observables``, already checked)."""
    return {name: mask(text, scene.grid.cells, scene.grid.lengths) for name, text in scene.stats.observables}
