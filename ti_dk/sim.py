"""The run controller: Taichi start-up, the time loop, statistics cadence, output and diagnostics."""
from __future__ import annotations

import ctypes
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import taichi as ti
from tqdm import tqdm

from . import initial
from .config import ConfigError, Scene
from .fv import SPDESolver
from .grid import Grid
from .hybrid import HybridSolver
from .io import RunFile
from .particles import ParticleSolver
from .stats import CellStats

ARCHS = {"cpu": ti.cpu, "cuda": ti.cuda}


class SimulationError(RuntimeError):
    """The run went wrong in a way the user can fix (unstable scheme, too many particles)."""


def init(arch: str = "cpu", threads: int | None = None) -> None:
    """Start Taichi on ``arch`` ('cpu' or 'cuda'); refuse a backend that is absent or unsupported.

    Literals in kernels are f64 (``default_fp``); solvers cast them to their own precision.
    """
    if arch not in ARCHS:
        raise ConfigError(f"backend '{arch}' is not supported: use --arch cpu or --arch cuda")
    if threads is not None and threads < 1:
        raise ConfigError(f"threads = {threads}: give at least 1 CPU thread")
    if arch == "cuda" and not _cuda_driver_present():
        raise ConfigError("the 'cuda' backend is not available on this machine (no CUDA driver): run with --arch cpu")
    kw = {"cpu_max_num_threads": threads} if threads else {}
    ti.init(arch=ARCHS[arch], default_fp=ti.f64, offline_cache=True, log_level=ti.WARN, **kw)
    if ti.lang.impl.current_cfg().arch != ARCHS[arch]:
        raise ConfigError(f"the '{arch}' backend is not available on this machine: run with --arch cpu")


def _cuda_driver_present() -> bool:
    try:
        ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    return True


def _initialized() -> bool:
    return ti.lang.impl.get_runtime().prog is not None


@dataclass(frozen=True)
class Stats:
    """Per-row, per-cell statistics; mean and variance in number density (particles per volume)."""

    mean: np.ndarray
    variance: np.ndarray
    skewness: np.ndarray
    kurtosis: np.ndarray
    n_samples: np.ndarray
    histogram: np.ndarray | None = None  # particles per cell, bins hist_lo … (one particle wide)
    hist_lo: int | None = None


@dataclass(frozen=True)
class Result:
    scene: Scene
    times: np.ndarray
    cell_volume: float
    stats: Stats
    diagnostics: dict[str, np.ndarray] = field(repr=False)
    final_density: np.ndarray = field(repr=False)  # every member at the end, (ensemble, *cells)
    wall_time: float = 0.0
    regrids: list[dict] = field(default_factory=list, repr=False)  # hybrid: one record per regrid
    path: Path | None = None


def make_solver(scene: Scene, ppc: np.ndarray):
    """The solver object for ``scene.method``, initialised from ``ppc`` particles per cell."""
    grid = Grid.from_scene(scene)
    real = ti.f32 if scene.precision == "f32" else ti.f64
    common = dict(grid=grid, dt=scene.dt, ensemble=scene.ensemble, seed=scene.seed, real=real)
    if scene.method == "particle":
        solver = ParticleSolver(capacity=ParticleSolver.capacity_for(grid, ppc), **common)
        solver.initialize(ppc, exact_uniform=scene.particle_init == "exact_uniform")
        return solver
    gaussian = "gaussian" in (scene.method, scene.spde if scene.method == "hybrid" else None)
    solver = SPDESolver(gaussian=gaussian, **common)
    solver.initialize(ppc)
    if scene.method == "hybrid":
        solver = HybridSolver(solver, scene.regrid, scene.regrid_interval, scene.seed, scene.ghost_profile)
        solver.initialize()
    return solver


def run(scene: Scene, out: str | Path | None = None, progress: bool | None = None,
        arch: str = "cpu", threads: int | None = None) -> Result:
    """Run a scene; return its statistics and, with ``out``, write ``out/<scene>_<method>.h5``.

    Rows are taken at ``scene.output_steps`` over the ensemble; a stationary scene (``t_equil``
    set) pools every ``sample_every``-th step after ``t_equil`` into one row.
    """
    if not _initialized():
        init(arch, threads)
    wall0 = time.perf_counter()
    ppc = initial.density_ppc(scene.init, scene.params, scene.cells, scene.lengths)
    try:
        solver = make_solver(scene, ppc)
    except OverflowError as exc:
        raise SimulationError(str(exc)) from None
    hist = scene.histogram
    path = Path(out) / f"{scene.name}_{scene.method}.h5" if out is not None else None
    rf = RunFile(path, scene, hist[1] - hist[0] + 1 if hist else None) if path else None
    rows: list[dict] = []
    times: list[float] = []
    diag: dict[str, list] = {"time": []}  # per step: every key the solver reports
    flushed = 0
    stationary = scene.t_equil is not None
    n_equil = round(scene.t_equil / scene.dt) if stationary else 0
    pooled = CellStats(scene.cells, scene.cell_volume, hist)
    outputs = set(scene.output_steps)

    def record(n: int) -> None:
        nonlocal flushed
        if stationary:
            if n >= n_equil and (n - n_equil) % scene.sample_every == 0:
                pooled.add(solver.density())
            if n != scene.n_steps:
                return
            row = pooled.row()
        elif n in outputs:
            cs = CellStats(scene.cells, scene.cell_volume, hist)
            cs.add(solver.density())
            row = cs.row()
        else:
            return
        rows.append(row)
        times.append(n * scene.dt)
        if rf:
            rf.write_row(n * scene.dt, row)
            rf.write_diagnostics({k: v[flushed:] for k, v in diag.items()})
            flushed = len(diag["time"])

    show = sys.stderr.isatty() if progress is None else progress
    try:
        record(0)
        with tqdm(total=scene.n_steps, disable=not show, unit="step", desc=f"{scene.name}/{scene.method}",
                  file=sys.stderr, mininterval=0.5) as bar:
            for n in range(scene.n_steps):
                solver.step(n)
                d = solver.diagnostics()
                if not math.isfinite(d["mass"]):
                    raise SimulationError(
                        f"the density became NaN or infinite at step {n + 1} (t = {(n + 1) * scene.dt:.4g}): "
                        f"the scheme is unstable at C = {scene.C}; lower C")
                diag["time"].append((n + 1) * scene.dt)
                for k, v in d.items():
                    diag.setdefault(k, []).append(v)
                record(n + 1)
                bar.update()
    except OverflowError as exc:
        if rf:
            rf.close(time.perf_counter() - wall0, error=str(exc))
        raise SimulationError(str(exc)) from None
    except BaseException as exc:
        if rf:
            rf.close(time.perf_counter() - wall0, error=f"{type(exc).__name__}: {exc}")
        raise
    wall = time.perf_counter() - wall0
    regrids = getattr(solver, "regrids", [])
    if rf:
        rf.write_table("regrid", regrids)
        rf.close(wall)
    stack = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    stats = Stats(mean=stack["mean"], variance=stack["variance"], skewness=stack["skewness"],
                  kurtosis=stack["kurtosis"], n_samples=stack["n_samples"], histogram=stack.get("histogram"),
                  hist_lo=hist[0] if hist else None)
    return Result(scene=scene, times=np.array(times), cell_volume=scene.cell_volume, stats=stats,
                  diagnostics={k: np.asarray(v) for k, v in diag.items()}, final_density=solver.density(),
                  wall_time=wall, path=path, regrids=regrids)
