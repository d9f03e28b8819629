"""The method registry: each scene ``method`` name and the builder of its solver, above the methods,
the hybrid and the scene it assembles."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import taichi as ti

from ..core import rng
from ..core.grid import Grid
from ..hybrid.solver import HybridSolver
from ..methods.fv import SPDESolver
from ..methods.particles import ParticleSolver
from ..methods.solver import Solver
from ..scene.estimates import hybrid_slots
from ..scene.schema import Scene

Builder = Callable[[Scene, np.ndarray, dict], Solver]  # (scene, particles per cell, common arguments) → solver


def make_solver(scene: Scene, ppc: np.ndarray, member0: int = 0) -> Solver:
    """The solver object for ``scene.method.name``, initialised from ``ppc`` particles per cell; its
    members are members ``member0 …`` of the whole ensemble (chunks of a distributed run)."""
    grid = Grid.from_scene(scene)
    real = ti.f32 if scene.method.precision == "f32" else ti.f64
    key = rng.device_key(rng.seed_key(scene.method.seed), member0)  # the one Philox key every solver of the run draws with
    common = dict(grid=grid, dt=scene.dt, ensemble=scene.method.ensemble, key=key, real=real, member0=member0)
    return BUILDERS[scene.method.name](scene, ppc, common)


def _spde(ppc: np.ndarray, common: dict, gaussian: bool, track_mean: bool = False) -> SPDESolver:
    solver = SPDESolver(gaussian=gaussian, track_mean=track_mean, **common)
    solver.initialize(ppc)
    return solver


def _particle(scene: Scene, ppc: np.ndarray, common: dict) -> ParticleSolver:
    capacity = ParticleSolver.capacity_for(common["grid"], ppc)  # its memory was checked with the scene
    solver = ParticleSolver(capacity=capacity, **common)
    solver.initialize(ppc, exact_uniform=scene.method.particle_init == "exact_uniform",
                      exact=scene.method.particle_init == "exact")
    return solver


def _hybrid(scene: Scene, ppc: np.ndarray, common: dict) -> HybridSolver:
    spde = _spde(ppc, common, gaussian=scene.hybrid.spde == "gaussian", track_mean=scene.hybrid.ghost_profile == "mean" or scene.hybrid.region_from == "mean")
    solver = HybridSolver(spde, scene.hybrid.regrid, scene.hybrid.regrid_interval, scene.hybrid.ghost_profile,
                          scene.hybrid.particle_substeps, scene.hybrid.pool_layout, hybrid_slots(scene))
    solver.initialize()
    return solver


BUILDERS: dict[str, Builder] = {  # every name in ti_dk.scene.schema.METHODS
    "fv": lambda scene, ppc, common: _spde(ppc, common, gaussian=False),
    "gaussian": lambda scene, ppc, common: _spde(ppc, common, gaussian=True),
    "particle": _particle,
    "hybrid": _hybrid,
}
