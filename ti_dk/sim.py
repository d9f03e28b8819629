"""The run controller: Taichi start-up, the time loop, statistics cadence, output and diagnostics."""
from __future__ import annotations

import contextlib
import ctypes
import io
import json
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import taichi as ti
from tqdm import tqdm

from .config import ConfigError, Scene, check_options
from .fv import SPDESolver
from .grid import Grid
from .hybrid import HybridSolver
from .io import (
    Outputs,
    RunFile,
    atomic_h5,
    output_error,
    read_group,
    read_rows,
    require_space,
    same_scene,
    scene_json,
    write_group,
    write_openpmd,
    write_rows,
)
from .particles import ParticleSolver
from .stats import CellStats

ARCHS = {"cpu": ti.cpu, "cuda": ti.cuda}
FLUSH_SECONDS = 5.0  # per-step diagnostics reach the file at least this often (and at every checkpoint)


class SimulationError(RuntimeError):
    """The run went wrong in a way the user can fix (unstable scheme, too many particles)."""


class Stopped(SimulationError):
    """SIGTERM or SIGINT arrived: the run stopped between two steps, its output closed and marked
    incomplete. ``status``: the exit status a shell gives for that signal (143, 130)."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status


_STOP: dict = {"signal": None}  # set by the handlers of stop_on_signals(), read between steps


@contextlib.contextmanager
def stop_on_signals():
    """SIGTERM and SIGINT set a flag that the run checks between steps (and after Taichi's start and
    the kernels' compilation), instead of raising wherever Python happens to be; handlers restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    def handler(signum, frame):
        if _STOP["signal"] is not None:  # asked twice: stop at once, the default way
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
        _STOP["signal"] = signum

    _STOP["signal"] = None
    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        _STOP["signal"] = None


def check_stop(where: str = " before the first step", rf=None, checkpoint: Path | None = None) -> None:
    """Raise :class:`Stopped` if a signal arrived: ``rf`` closed and marked incomplete with the reason,
    and the message names the latest checkpoint only if there is one."""
    signum = _STOP["signal"]
    if signum is None:
        return
    name = signal.Signals(signum).name
    if rf is not None:
        rf.close(error=f"stopped by {name}{where}")
    msg = f"stopped by {name}{where}"
    msg += f"; {rf.path} is marked incomplete" if rf is not None else ""
    msg += f"; resume with --restart {checkpoint}" if checkpoint is not None else ""
    raise Stopped(msg, 128 + signum)


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
    with contextlib.redirect_stdout(io.StringIO()):  # ti.init prints "[Taichi] Starting on arch=..." unasked
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
    timing: dict[str, float] = field(default_factory=dict)  # seconds per part of the run
    frames: list[Path] = field(default_factory=list)  # PNG frames written
    written: dict[str, Path] = field(default_factory=dict)  # every file or folder written, by what it holds
    rows: list[dict] = field(default_factory=list, repr=False)  # statistics rows with their accumulators
    chunks: dict = field(default_factory=dict)  # distributed runs: chunk count and the retried chunks
    path: Path | None = None


def make_solver(scene: Scene, ppc: np.ndarray, member0: int = 0):
    """The solver object for ``scene.method.name``, initialised from ``ppc`` particles per cell; its
    members are members ``member0 …`` of the whole ensemble (chunks of a distributed run)."""
    grid = Grid.from_scene(scene)
    real = ti.f32 if scene.method.precision == "f32" else ti.f64
    common = dict(grid=grid, dt=scene.dt, ensemble=scene.method.ensemble, seed=scene.method.seed, real=real, member0=member0)
    if scene.method.name == "particle":
        capacity = ParticleSolver.capacity_for(grid, ppc)  # its memory was checked with the scene
        solver = ParticleSolver(capacity=capacity, **common)
        solver.initialize(ppc, exact_uniform=scene.method.particle_init == "exact_uniform")
        return solver
    gaussian = "gaussian" in (scene.method.name, scene.hybrid.spde if scene.method.name == "hybrid" else None)
    mean_ghosts = scene.method.name == "hybrid" and scene.hybrid.ghost_profile == "mean"  # ghosts read q̄
    solver = SPDESolver(gaussian=gaussian, track_mean=mean_ghosts, **common)
    solver.initialize(ppc)
    if scene.method.name == "hybrid":
        solver = HybridSolver(solver, scene.hybrid.regrid, scene.hybrid.regrid_interval, scene.method.seed, scene.hybrid.ghost_profile,
                              scene.hybrid.particle_substeps)
        solver.initialize()
    return solver


@dataclass
class _Progress:
    """What a run has produced so far: enough, with the solver states, to resume it exactly."""

    step: int = 0
    rows: list = field(default_factory=list)  # statistics rows (dicts of arrays)
    times: list = field(default_factory=list)  # their times
    diag: dict = field(default_factory=lambda: {"time": []})  # per step: every key the solvers report
    frames: dict = field(default_factory=lambda: {"time": [], "negative_cells": []})  # per frame
    pooled: dict | None = None  # stationary runs: the pooled accumulator's state
    timing: dict = field(default_factory=dict)  # seconds per part of the run


def run(scene: Scene, out: str | Path | None = None, progress: bool | None = None,
        arch: str = "cpu", threads: int | None = None, *, frames: bool | None = None, movie: bool = False,
        snapshots: bool | None = None, checkpoint_every: int = 0, restart: str | Path | None = None,
        member0: int = 0, overwrite: bool = False) -> Result:
    """Run a scene; return its statistics and, with ``out``, write its files there.

    Rows are taken at ``scene.output_steps`` over the ensemble; a stationary scene (``t_equil``
    set) pools every ``sample_every``-th step after ``t_equil`` into one row. With ``out``:
    ``<scene>_<method>.h5`` (statistics, diagnostics), by default PNG frames at the output times
    (``frames``: 2D/3D densities of member 0, 1D moment profiles; ``movie`` adds
    ``scene.output.movie_frames`` evenly spaced frames and ``<scene>_<method>.mp4``) and, for 2D/3D
    scenes, openPMD snapshots of member 0 (``snapshots``).
    ``checkpoint_every`` K writes ``<scene>_<method>_checkpoint.h5`` every K steps (atomically);
    ``restart`` continues from such a file, bit for bit as if never interrupted. ``member0``: the
    global index of the first member (a chunk of a larger ensemble, see :mod:`ti_dk.ensemble`).

    Every path lies inside ``out`` (:class:`ti_dk.io.Outputs`); the run holds an exclusive lock on
    it, so a second run there is refused, and replaces a complete result only with ``overwrite``.
    A signal seen by :func:`stop_on_signals` stops it between steps (:class:`Stopped`); an I/O
    failure raises :class:`ti_dk.io.OutputError`; both leave the file marked incomplete.
    """
    check_options(scene, out=out, threads=threads, checkpoint_every=checkpoint_every, restart=restart, movie=movie)
    if out is None:
        return _run(scene, None, progress, arch, threads, frames, movie, snapshots, checkpoint_every, restart, member0)
    outputs = Outputs.of(out, scene)
    with outputs.claim(overwrite, fresh=restart is None):
        try:
            return _run(scene, outputs, progress, arch, threads, frames, movie, snapshots, checkpoint_every, restart,
                        member0)
        except OSError as exc:  # disk full, quota, permission: the run file is already closed
            raise output_error(outputs.out, exc) from None


def _run(scene: Scene, outputs_: Outputs | None, progress, arch, threads, frames, movie, snapshots, checkpoint_every,
         restart, member0) -> Result:
    """The time loop of :func:`run`, on checked options and a claimed output."""
    if not _initialized():
        init(arch, threads)
    check_stop()
    wall0 = time.perf_counter()
    ppc = scene.initial_ppc
    try:
        solver = make_solver(scene, ppc, member0)
        other = make_solver(scene.replace(method=scene.method.compare), ppc, member0) if scene.method.compare else None
    except OverflowError as exc:
        raise SimulationError(str(exc)) from None
    prog = _Progress()
    if restart is not None:
        prog = _read_checkpoint(Path(restart), scene, solver, other)
    frames = outputs_ is not None and (frames is not False or movie)  # 1D: moment profiles
    snapshots = outputs_ is not None and scene.grid.dim >= 2 and snapshots is not False  # snapshots: 2D and 3D
    hist = scene.stats.histogram
    rf = RunFile(outputs_.run_file, scene, hist[1] - hist[0] + 1 if hist else None) if outputs_ else None
    if rf:  # a restarted run writes what the checkpoint holds first: the file ends up the same
        for t, row in zip(prog.times, prog.rows):
            rf.write_row(t, row)
    sink = _DiagnosticsSink(rf, prog.diag)
    sink.flush(force=True)
    writer = None
    written = {"statistics and diagnostics": rf.path} if rf else {}
    if frames:
        from .render import FrameWriter

        writer = FrameWriter(outputs_.frames, _renderer(scene, ppc, other))
        writer.files = [writer.dir / f"frame_{k:04d}.png" for k in range(len(prog.frames["time"]))]
        written["frames"] = writer.dir
    stationary = scene.stats.t_equil is not None
    n_equil = round(scene.stats.t_equil / scene.dt) if stationary else 0
    pooled = CellStats(scene.grid.cells, scene.grid.cell_volume, hist)
    if prog.pooled:
        pooled.load_state(prog.pooled)
    outputs = set(scene.output_steps)
    profile = scene.grid.dim == 1  # 1D frames draw the ensemble's statistics: rows at every frame step
    frame_steps = set(scene.output_steps) | ({0} if frames and not profile else set())
    if movie and not stationary:
        frame_steps |= {round(k * scene.n_steps / scene.output.movie_frames) for k in range(scene.output.movie_frames + 1)}
    timing = prog.timing
    for part in ("setup", "compile", "statistics", "render", "io"):
        timing.setdefault(part, 0.0)

    def clock(part: str, t0: float) -> float:
        t1 = time.perf_counter()
        timing[part] = timing.get(part, 0.0) + t1 - t0
        return t1

    def record(n: int) -> None:
        t0 = time.perf_counter()
        t = n * scene.dt
        if stationary:
            if n >= n_equil and (n - n_equil) % scene.stats.sample_every == 0:
                pooled.add(solver.density())
            row = pooled.row() if n == scene.n_steps else None
        elif n in outputs or (frames and profile and n in frame_steps):
            cs = CellStats(scene.grid.cells, scene.grid.cell_volume, hist)
            cs.add(solver.density())
            row = cs.row()
        else:
            row = None
        t0 = clock("statistics", t0)
        if frames and n in frame_steps and profile:
            region = solver.region().mean(axis=0) if isinstance(solver, HybridSolver) else None
            writer.write(t, row, region)
            prog.frames["time"].append(t)
            prog.frames["negative_cells"].append(int((solver.density() < 0).sum()))  # all members
            t0 = clock("render", t0)
        elif frames and n in frame_steps:
            panels = _panels(scene, solver, other)
            writer.write(t, panels)
            prog.frames["time"].append(t)
            prog.frames["negative_cells"].append(int((panels[0].ppc < 0).sum()))
            if other:
                prog.frames.setdefault("compare_negative_cells", []).append(int((panels[1].ppc < 0).sum()))
            t0 = clock("render", t0)
        if snapshots and n in outputs:
            _snapshot(outputs_.snapshots, n, scene, solver)
        if row is not None and n in outputs:
            prog.rows.append(row)
            prog.times.append(t)
            if rf:
                rf.write_row(t, row)
        sink.flush(force=row is not None)
        clock("io", t0)

    show = sys.stderr.isatty() if progress is None else progress
    ckpt = outputs_.checkpoint if outputs_ and checkpoint_every else None
    latest = Path(restart) if restart is not None else None  # the checkpoint a stopped run can resume from
    if snapshots:
        written["openPMD snapshots"] = outputs_.snapshots
    if ckpt:
        written["checkpoint"] = ckpt
    clock("setup", wall0)  # solvers built and initialised (their kernels compiled), checkpoint read
    label = f"{scene.name}/{scene.method.name}"
    try:
        if restart is None:
            record(0)
        with tqdm(total=scene.n_steps, initial=prog.step, disable=not show, unit="step",
                  desc=f"{label}: compiling", file=sys.stderr, mininterval=0.5) as bar:
            first = True  # the first step compiles the step kernels: timed as "compile", not in the ETA
            for n in range(prog.step, scene.n_steps):
                check_stop(f" at step {n} of {scene.n_steps}", rf, latest)
                t0 = time.perf_counter()
                if first:
                    before, t_first = _parts(timing, solver), t0
                solver.step(n)
                t0 = clock("solver", t0)
                d = solver.diagnostics()
                if other:
                    other.step(n)
                    clock("compare", t0)
                    d |= {f"compare_{k}": v for k, v in other.diagnostics().items()
                          if k in ("mass", "min_density", "negative_cells")}
                if not math.isfinite(d["mass"]):
                    raise SimulationError(
                        f"the density became NaN or infinite at step {n + 1} (t = {(n + 1) * scene.dt:.4g}): "
                        f"the scheme is unstable at C = {scene.time.C}; lower C")
                prog.diag["time"].append((n + 1) * scene.dt)
                for k, v in d.items():
                    prog.diag.setdefault(k, []).append(v)
                record(n + 1)
                prog.step = n + 1
                if ckpt and prog.step % checkpoint_every == 0 and prog.step < scene.n_steps:
                    t0 = time.perf_counter()
                    prog.pooled = pooled.state() if stationary else None
                    _write_checkpoint(ckpt, scene, solver, other, prog)
                    latest = ckpt
                    sink.flush(force=True)
                    clock("io", t0)
                if not first:
                    bar.update()
                else:
                    first = False
                    for k, v in _parts(timing, solver).items():  # move the first step into "compile"
                        (solver.timing if k in getattr(solver, "timing", {}) else timing)[k] -= v - before.get(k, 0.0)
                    clock("compile", t_first)
                    bar.set_description(label, refresh=False)
                    bar.reset()  # restart the rate and ETA clock after compilation
                    bar.initial = bar.n = bar.last_print_n = prog.step
                    bar.refresh()
        if movie and writer:
            t0 = time.perf_counter()
            written["movie"] = writer.movie(outputs_.movie)
            clock("render", t0)
    except OverflowError as exc:
        if rf:
            rf.close(time.perf_counter() - wall0, error=str(exc))
        raise SimulationError(str(exc)) from None
    except BaseException as exc:
        if rf:
            _close_quietly(rf, time.perf_counter() - wall0, f"{type(exc).__name__}: {exc}")
        raise
    wall = time.perf_counter() - wall0
    if hasattr(solver, "timing"):  # the hybrid splits its step into SPDE, particles and regrid
        timing.update({k: v for k, v in solver.timing.items()})
        timing.pop("solver", None)
    timing = {k: timing[k] for k in TIMING_ORDER if k in timing}  # the parts in step order
    timing["other"] = wall - sum(timing.values())  # progress bar, diagnostics, closing files
    timing["total"] = wall
    regrids = getattr(solver, "regrids", [])
    if rf:
        rf.write_table("regrid", regrids)
        if frames:
            rf.write_table("frames", [dict(zip(prog.frames, v)) for v in zip(*prog.frames.values())])
        rf.h5.attrs["timing"] = json.dumps(timing)
        rf.close(wall)
    stats = stats_of(prog.rows, hist)
    return Result(scene=scene, times=np.array(prog.times), cell_volume=scene.grid.cell_volume, stats=stats,
                  diagnostics={k: np.asarray(v) for k, v in prog.diag.items()}, final_density=solver.density(),
                  wall_time=wall, path=rf.path if rf else None, regrids=regrids, timing=timing,
                  frames=list(writer.files) if writer else [], rows=prog.rows, written=written)


TIMING_ORDER = ("setup", "compile", "regrid", "spde", "particles", "solver", "compare", "statistics", "render", "io")


def _parts(timing: dict, solver) -> dict[str, float]:
    """Seconds spent so far in each part of the run, the hybrid's own parts included."""
    return timing | getattr(solver, "timing", {})


def _renderer(scene: Scene, ppc: np.ndarray, other):
    """What draws this scene's frames: moment profiles in 1D, density panels in 2D and 3D."""
    if scene.grid.dim == 1:
        from .profiles import ProfileRenderer

        return ProfileRenderer(scene)
    from .render import Renderer, colour_max

    methods = scene.method.name + (f" (left) and {scene.method.compare} (right)" if other and scene.grid.dim == 2 else
                              f" (top) and {scene.method.compare} (bottom)" if other else "")
    return Renderer(scene.grid.cells, scene.grid.lengths, 1 + bool(other), colour_max(ppc),
                    f"{scene.name}: {methods}, {'×'.join(map(str, scene.grid.cells))} cells, member 0")


def summary(result: Result) -> str:
    """The end-of-run message: what ran, every method's negative cells, where the time went (in
    step order, compilation apart) and every file written."""
    sc, d, E = result.scene, result.diagnostics, result.scene.method.ensemble
    members = f"{E:,} member{'s' * (E != 1)}"
    every = " (all members)" if E > 1 else ""
    t = result.times[-1] if len(result.times) else sc.n_steps * sc.dt
    lines = [f"{sc.name}/{sc.method.name}: {sc.n_steps:,} steps of dt = {sc.dt:.4g} to t = {t:.4g}, {members}, "
             f"{result.wall_time:.1f} s"]
    mass = f"{d['mass'][-1] / E:,.6g} particles{' per member' * (E > 1)}" if "mass" in d else None

    def negative(prefix: str) -> str:
        neg = d.get(f"{prefix}negative_cells")
        if neg is None or not len(neg):
            return "negative cells not recorded"
        return f"negative cells{every} {int(neg[-1]):,} at the end, at most {int(np.max(neg)):,} in a step"

    main = [negative(""), *([mass] if mass else [])]
    if "particles" in d:
        n = d["particles"][-1] / E
        where = f"{n:,.1f}" if E > 1 else f"{int(n):,}"
        where += f" particles{' per member' * (E > 1)} in the particle region"
        if sc.hybrid.regrid_interval == 0:
            covered = f": {result.regrids[0]['covered_cells'] / E:,.0f} cells{' per member' * (E > 1)}" \
                if result.regrids else ""
            where += f" (fixed at the start{covered})"
        else:
            where += f" after {len(result.regrids):,} regrids"
        main.append(where)
    lines.append(f"  {sc.method.name}: " + "; ".join(main))
    if sc.method.compare and "compare_negative_cells" in d:
        lines.append(f"  {sc.method.compare} (run alongside): {negative('compare_')}")
    names = {"compile": "compile (first step)", "solver": sc.method.name}
    parts = [f"{names.get(k, k)} {v:.2f} s" for k, v in result.timing.items() if k != "total"]
    if parts:
        lines.append("time: " + ", ".join(parts) + f"; total {result.wall_time:.2f} s")
    written = result.written or ({"statistics and diagnostics": result.path} if result.path else {})
    if written:
        lines.append("wrote:")
    for what, path in written.items():
        path = Path(path)
        if what == "frames":
            count = f"{len(result.frames)} PNG frame{'s' * (len(result.frames) != 1)}"
            lines.append(f"  {path}/  ({count})")
        elif path.is_dir():
            lines.append(f"  {path}/  ({what}: {sum(1 for _ in path.iterdir())} files)")
        else:
            lines.append(f"  {path}  ({what})")
    return "\n".join(lines)


class _DiagnosticsSink:
    """Per-step diagnostics on their way to the run file: written with every statistics row, at
    every checkpoint and at least every ``FLUSH_SECONDS``, so a killed run keeps them up to then."""

    def __init__(self, rf: RunFile | None, diag: dict):
        self.rf, self.diag, self.done, self.last = rf, diag, 0, time.monotonic()

    def flush(self, force: bool = False) -> None:
        if self.rf is None or not (force or time.monotonic() - self.last > FLUSH_SECONDS):
            return
        n = len(self.diag["time"])
        if n > self.done:
            self.rf.write_diagnostics({k: v[self.done:] for k, v in self.diag.items()})
        self.done, self.last = n, time.monotonic()


def _close_quietly(rf: RunFile, wall: float, error: str) -> None:
    """Mark ``rf`` incomplete on the way out of a failed run; a second failure (the disk still full)
    must not hide the first."""
    try:
        rf.close(wall, error=error)
    except OSError:
        pass


def stats_of(rows: list[dict], hist: tuple[int, int] | None) -> Stats:
    """The rows stacked along time."""
    stack = {k: np.stack([r[k] for r in rows]) for k in rows[0] if not k.startswith("acc_")}
    return Stats(mean=stack["mean"], variance=stack["variance"], skewness=stack["skewness"],
                 kurtosis=stack["kurtosis"], n_samples=stack["n_samples"], histogram=stack.get("histogram"),
                 hist_lo=hist[0] if hist else None)


def _panels(scene: Scene, solver, other) -> list:
    """Member 0 of each method as a frame panel, in particles per cell."""
    from .render import Panel

    vol = scene.grid.cell_volume
    panels = [Panel(scene.method.name, solver.density()[0] * vol, getattr(solver, "boxes", [None])[0])]
    if other:
        panels.append(Panel(scene.method.compare, other.density()[0] * vol))
    return panels


def _snapshot(directory: Path, n: int, scene: Scene, solver) -> None:
    """openPMD snapshot of member 0 at step ``n`` (the hybrid adds its region, particles and boxes)."""
    region = positions = ids = boxes = None
    if isinstance(solver, HybridSolver):
        region = solver.region()[0]
        st = solver.state()
        k = int(st["n_real"][0])
        positions = st["x"][0, :k]
        ids = (st["pid"][0, :k, 0].astype(np.uint64) << np.uint64(32)) | st["pid"][0, :k, 1].astype(np.uint64)
        boxes = np.array([(*lo, *hi) for lo, hi in solver.boxes[0]], dtype=np.int64).reshape(-1, 2 * scene.grid.dim)
    write_openpmd(directory, n, n * scene.dt, scene.dt, Grid.from_scene(scene),
                  solver.density()[0], region, positions, ids, boxes)


def _write_checkpoint(path: Path, scene: Scene, solver, other, prog: _Progress) -> None:
    """Everything needed to resume at ``prog.step``; written to a temporary name, then renamed."""
    states = {name: s.state() for name, s in (("solver", solver), ("compare", other)) if s is not None}
    require_space(path, sum(v.nbytes for st in states.values() for v in st.values()))
    with atomic_h5(path) as f:  # interrupted (SIGTERM): the previous checkpoint stays the latest
        f.attrs["scene"] = scene_json(scene)
        f.attrs["step"] = prog.step
        f.attrs["timing"] = json.dumps(prog.timing | ({"hybrid": solver.timing} if hasattr(solver, "timing") else {}))
        for name, st in states.items():
            write_group(f, name, st)
        f.create_dataset("times", data=np.array(prog.times, dtype=np.float64))
        write_rows(f, prog.rows)
        write_group(f, "diag", prog.diag)
        write_group(f, "frames", prog.frames)
        write_group(f, "pooled", prog.pooled or {})


def _read_checkpoint(path: Path, scene: Scene, solver, other) -> _Progress:
    """The progress a checkpoint holds, loaded into the solvers after :func:`_checkpoint_problem`
    found nothing wrong with it; anything else is refused with one line."""
    damaged = f"--restart {path}: damaged checkpoint"
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ConfigError(f"--restart {path}: not a readable checkpoint ({str(exc).splitlines()[0]}); give a file "
                          "written by --checkpoint-every") from None
    with f:
        try:
            if "scene" not in f.attrs or "step" not in f.attrs:
                raise ConfigError(f"--restart {path}: not a ti_dk checkpoint; give a file written by --checkpoint-every")
            if not same_scene(f, scene):
                raise ConfigError(f"--restart {path}: the checkpoint was written for other scene settings; "
                                  "restart with the same scene, method and --set values")
            states = {name: read_group(f[name]) for name in ("solver", "compare") if name in f}
            timing = json.loads(f.attrs["timing"])
            prog = _Progress(step=int(f.attrs["step"]), times=list(f["times"][()]), timing=timing, rows=read_rows(f),
                             diag={k: list(v) for k, v in read_group(f["diag"]).items()},
                             frames={k: list(v) for k, v in read_group(f["frames"]).items()},
                             pooled=read_group(f["pooled"]) or None if "pooled" in f else None)
        except (KeyError, ValueError, TypeError, OSError) as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError(f"{damaged} ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); "
                              "restart from another checkpoint or from the start") from None
    try:
        problem = _checkpoint_problem(scene, prog, states, {"solver": solver, "compare": other})
    except (KeyError, IndexError, ValueError) as exc:  # a table missing or cut short
        problem = f"{type(exc).__name__} {exc}"
    if problem:
        raise ConfigError(f"{damaged}: {problem}; restart from another checkpoint or from the start")
    solver.load_state(states["solver"])
    if other is not None:
        other.load_state(states["compare"])
    if "hybrid" in prog.timing:
        solver.timing = prog.timing.pop("hybrid")
    return prog


_VARIABLE = ("x", "pid", "boxes")  # hybrid state whose length changes with the particles (and regrid_*)


def _checkpoint_problem(scene: Scene, prog: _Progress, states: dict, solvers: dict) -> str | None:
    """What is wrong with a checkpoint's content, or None: step and row counts, the state's keys,
    shapes and types (against a fresh solver's), finite values, particles inside the domain and,
    for the hybrid, in their region, and the mass the state holds against the diagnostics."""
    step, n = prog.step, scene.n_steps
    missing = {"time", "mass"} - set(prog.diag)
    if missing:
        return f"its diagnostics lack {', '.join(sorted(missing))}"
    if not 0 < step < n:
        return f"step {step} is outside 1 … {n - 1}"
    if any(len(v) != step for v in prog.diag.values()) or not math.isclose(prog.diag["time"][-1], step * scene.dt,
                                                                           rel_tol=1e-9):
        return f"its per-step diagnostics do not end at step {step}"
    rows = 0 if scene.stats.t_equil is not None else sum(1 for s in scene.output_steps if s <= step)
    if len(prog.rows) != rows or len(prog.times) != rows:
        return f"it holds {len(prog.rows)} statistics rows where step {step} has {rows}"
    for name, solver in solvers.items():
        if solver is None:
            continue
        if name not in states:
            return f"the {name} state is missing"
        st, fresh = states[name], solver.state()
        if set(st) != set(fresh):
            return f"the {name} state has keys {sorted(st)}, not {sorted(fresh)}"
        for k, v in st.items():
            variable = k in _VARIABLE or k.startswith("regrid_")
            if v.dtype != fresh[k].dtype or (v.shape != fresh[k].shape if not variable else v.ndim != fresh[k].ndim):
                return f"{name}/{k} has shape {v.shape} {v.dtype}, not {fresh[k].shape} {fresh[k].dtype}"
            if v.dtype.kind == "f" and not k.startswith("regrid_") and not np.isfinite(v).all():
                return f"{name}/{k} holds NaN or infinite values"
        problem = _state_problem(scene, name, st, solver, prog.diag)
        if problem:
            return problem
    return None


def _state_problem(scene: Scene, name: str, st: dict, solver, diag: dict) -> str | None:
    """Particles inside the domain (and the hybrid's region), and the mass against the diagnostics."""
    vol, lengths = scene.grid.cell_volume, np.array(scene.grid.lengths)
    counts = st.get("n_alive", st.get("n_real"))
    if counts is not None:
        x = st["x"]
        if counts.shape != (scene.method.ensemble,) or counts.min() < 0 or counts.max() > x.shape[-2]:
            return f"{name}: particle counts {counts.tolist()[:4]} do not fit its {x.shape[-2]} slots"
        live = np.arange(x.shape[-2])[None, :] < counts[:, None]
        pos = x[live]
        if pos.size and ((pos < 0).any() or (pos >= lengths).any()):
            return f"{name}: particles lie outside the domain [0, {list(scene.grid.lengths)})"
    prefix = "" if name == "solver" else "compare_"
    if "n_alive" in st:
        mass = float(counts.sum())
    else:
        q = st["spde_q" if "spde_q" in st else "q"]
        mass = float(q.astype(np.float64).sum() * vol)
    if "n_real" in st:  # hybrid: covered cells hold exactly their particles, and the boxes cover the region
        cells = np.minimum((pos / np.array(scene.grid.dx)).astype(np.int64), np.array(scene.grid.cells) - 1)
        member = np.nonzero(live)[0]
        covered = st["covered"].astype(bool)
        if pos.size and not covered[(member, *cells.T)].all():
            return f"{name}: particles lie outside the particle region"
        count = np.zeros(covered.shape)
        np.add.at(count, (member, *cells.T), 1)
        if not np.allclose((st["spde_q"] * vol)[covered], count[covered], rtol=1e-6, atol=1e-6):
            return f"{name}: the densities of the particle region differ from its particle counts"
        region = np.zeros_like(covered)
        for e, *b in st["boxes"]:
            d = scene.grid.dim
            region[(e, *(slice(lo, hi) for lo, hi in zip(b[:d], b[d:])))] = True
        if not np.array_equal(region, covered):
            return f"{name}: the particle region differs from its boxes"
    want = float(diag[prefix + "mass"][-1])
    tol = 1e-5 if scene.method.precision == "f32" else 1e-9
    if not math.isclose(mass, want, rel_tol=tol, abs_tol=tol):
        return f"{name}: its state holds {mass:.10g} particles where the diagnostics say {want:.10g}"
    return None
