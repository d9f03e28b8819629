"""The run controller: a scene's solvers advanced step by step, each step followed by the output
handlers that are due (:mod:`ti_dk.control.handlers`), and the end-of-run summary."""
from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .checkpoint import Progress, read_checkpoint
from ..scene.estimates import work_estimate
from ..scene.checks import check_initial
from ..scene.load import scene_of
from .options import check_options
from ..scene.schema import Scene
from .handlers import Checkpoints, Clock, Diagnostics, Frames, Observations, Snapshots, Statistics
from ..output.claim import Outputs
from ..output.files import RunFile, is_complete, output_error
from ..output.series import summary_lines
from .registry import make_solver  # also where tests and benchmarks build a solver
from .runtime import Result, init, initialized, started_here, stats_of
from ..core.errors import SimulationError
from .signals import check_stop
from ..methods.solver import Solver

COMPARED = ("mass", "min_density", "negative_cells")  # diagnostics of the method run alongside, as compare_*


@dataclass(frozen=True)
class RunOptions:
    """How :func:`run` runs a scene, beyond the scene and its output folder."""

    progress: bool | None = None  # a progress bar on stderr (None: when stderr is a terminal)
    arch: str = "cpu"  # the Taichi backend, if Taichi is not started yet
    threads: int | None = None  # CPU threads, if Taichi is not started yet (None: all cores)
    frames: bool | None = None  # PNG frames at the output times (with an output; None: yes)
    movie: bool = False  # also scene.output.movie_frames evenly spaced frames and an MP4
    snapshots: bool | None = None  # openPMD snapshots of member 0, 2D/3D (with an output; None: yes)
    checkpoint_every: int = 0  # steps between checkpoints (0: none)
    restart: Path | None = None  # the checkpoint to continue from
    member0: int = 0  # the global index of the first member (a chunk of a larger ensemble)
    samples: bool = False  # keep every member's density behind each statistics row (Result.samples)


def run(scene: Scene | str | Path, out: str | Path | None = None, progress: bool | None = None,
        arch: str = "cpu", threads: int | None = None, *, frames: bool | None = None, movie: bool = False,
        snapshots: bool | None = None, checkpoint_every: int = 0, restart: str | Path | None = None,
        member0: int = 0, overwrite: bool = False, samples: bool = False) -> Result:
    """Run a scene (a :class:`Scene`, validated again here, or a scene name or path); return its
    statistics and, with ``out``, write its files there.

    Rows are taken at ``scene.output_steps`` over the ensemble; a stationary scene (``t_equil``
    set) pools every ``sample_every``-th step after ``t_equil`` into one row. With ``out``:
    ``<scene>_<method>.h5`` (statistics, diagnostics), by default PNG frames at the output times
    (``frames``: 2D/3D densities of member 0, 1D moment profiles; ``movie`` adds
    ``scene.output.movie_frames`` evenly spaced frames and ``<scene>_<method>.mp4``) and, for 2D/3D
    scenes, openPMD snapshots of member 0 (``snapshots``).
    ``checkpoint_every`` K writes ``<scene>_<method>_checkpoint.h5`` every K steps (atomically);
    ``restart`` continues from such a file, bit for bit as if never interrupted. ``member0``: the
    global index of the first member (a chunk of a larger ensemble, see :mod:`ti_dk.control.ensemble`).
    ``samples`` keeps every member's density behind each row in ``Result.samples`` (the
    speed/accuracy pilot of :mod:`ti_dk.control.tradeoff` needs more than the rows' moments).

    Every path lies inside ``out`` (:class:`ti_dk.output.claim.Outputs`); the run holds an exclusive
    lock on it, so a second run there is refused, and replaces a complete result only with
    ``overwrite`` and only once it has finished (the old one stays whole if it fails or stops).
    A signal seen by :func:`ti_dk.control.signals.stop_on_signals` stops it between steps
    (:class:`ti_dk.core.errors.Stopped`); an I/O failure raises :class:`ti_dk.OutputError`; both
    leave the file marked incomplete. Taichi runs on the thread that started it, one run at a time:
    a run from another thread, or while another goes, raises :class:`ti_dk.SimulationError`.
    """
    scene = scene_of(scene)
    check_options(scene, out=out, threads=threads, checkpoint_every=checkpoint_every, restart=restart, movie=movie,
                  frames=frames, member0=member0)
    opts = RunOptions(progress, arch, threads, frames, movie, snapshots, checkpoint_every,
                      Path(restart) if restart is not None else None, member0, samples)
    if not started_here():
        raise SimulationError("Taichi was started on another thread, and runs only on that one: call ti_dk.run "
                              "from the thread that started it, or run scenes in separate processes")
    if not _ONE_RUN.acquire(blocking=False):  # two at once crash Taichi (runtime.started_here)
        raise SimulationError("another ti_dk.run is going in this process, and Taichi runs one at a time: wait "
                              "for it to return, or run scenes in separate processes")
    try:
        if out is None:
            return _run(scene, None, opts)
        outputs = Outputs.of(out, scene)
        check_stop()
        with outputs.claim(overwrite, fresh=restart is None) as outputs:
            try:
                return _run(scene, outputs, opts)
            except OSError as exc:  # disk full, quota, permission: the run file is already closed
                raise output_error(outputs.out, exc) from None
    finally:
        _ONE_RUN.release()


_ONE_RUN = threading.Lock()  # held by the run going in this process (one at a time)


def _run(scene: Scene, outputs: Outputs | None, opts: RunOptions) -> Result:
    """The time loop of :func:`run`, on checked options and a claimed output."""
    if not initialized():
        init(opts.arch, opts.threads)
    check_stop()
    wall0 = time.perf_counter()
    ppc = check_initial(scene)  # a density file may have changed since the scene was loaded
    solver, other = _solvers(scene, ppc, opts.member0)
    prog = read_checkpoint(opts.restart, scene, solver, other) if opts.restart is not None else Progress()
    check_stop()
    ctl = Controller(scene, solver, other, outputs, prog, opts, wall0, ppc)
    ctl.clock.add("setup", wall0)  # solvers built and initialised (their kernels compiled), checkpoint read
    show = sys.stderr.isatty() if opts.progress is None else opts.progress
    try:
        if opts.restart is None:
            ctl.record(0)
        with StepBar(scene, prog.step, show, ctl.clock, work_estimate(scene)[1]) as bar:
            for n in range(prog.step, scene.n_steps):
                check_stop(f" at step {n} of {scene.n_steps}", ctl.stopped_file, ctl.checkpoints.latest)
                bar.starting()
                ctl.advance(n)
                ctl.record(n + 1)
                bar.stepped(n + 1)
        if opts.movie:
            ctl.make_movie()
        ctl.draw_structure_factor()
        ctl.draw_series()
    except OverflowError as exc:
        if ctl.rf:
            ctl.rf.close(ctl.wall(), error=str(exc))
        raise SimulationError(str(exc)) from None
    except BaseException as exc:
        if ctl.rf:
            _close_quietly(ctl, str(exc) if isinstance(exc, SimulationError) else f"{type(exc).__name__}: {exc}")
        raise
    return ctl.finish(ctl.wall())


def _solvers(scene: Scene, ppc: np.ndarray, member0: int) -> tuple[Solver, Solver | None]:
    """The scene's solver and that of the method run alongside (``scene.method.compare``), if any,
    from the initial density ``ppc``."""
    try:
        solver = make_solver(scene, ppc, member0)
        other = make_solver(scene.replace(method=scene.method.compare), ppc, member0) if scene.method.compare else None
    except OverflowError as exc:
        raise SimulationError(str(exc)) from None
    return solver, other


class Controller:
    """One run: its solvers (``other``: the method run alongside), the clock of its parts and its
    output handlers, asked in order after every step whether they are due."""

    def __init__(self, scene: Scene, solver: Solver, other: Solver | None, outputs: Outputs | None,
                 prog: Progress, opts: RunOptions, wall0: float, ppc: np.ndarray):
        self.scene, self.solver, self.other = scene, solver, other
        self.outputs = outputs  # every path the run writes, or None
        self.wall0 = wall0 - prog.wall  # when the run began (perf_counter), a restarted one's earlier part included
        self.clock = Clock(prog.timing, solver)  # seconds per part of the run
        self.rf = RunFile.of(outputs, scene) if outputs else None  # statistics and diagnostics
        frames = outputs is not None and (opts.frames is not False or opts.movie)
        steps = _frame_steps(scene, frames, opts.movie)
        self.statistics = Statistics(scene, solver, self.rf, prog, steps if frames and scene.grid.dim == 1 else (),
                                     opts.samples)
        sampled = scene.method.ensemble > 1 or scene.stats.t_equil is not None  # rows with a variance
        # where the last row's S(k) is drawn at the end, or None
        self.spectrum_png = outputs.structure_factor if frames and scene.stats.structure_factor and sampled else None
        self.observations = Observations(scene, solver, self.rf, prog.series)
        self.diagnostics = Diagnostics(self.rf, prog.diag, self.statistics, self.observations)
        # the series drawn at the end (output/series.py), or None
        self.series_png = outputs.series if frames else None
        self.observables_png = outputs.observables if frames and scene.stats.observables else None
        writer = _frame_writer(outputs, scene, other) if frames else None
        self.frames = Frames(scene, solver, other, writer, steps, prog.frames, self.statistics)
        draw_snapshots = outputs is not None and scene.grid.dim >= 2 and opts.snapshots is not False
        self.snapshots = Snapshots(scene, solver, outputs.staged(outputs.snapshots) if draw_snapshots else None)
        every = opts.checkpoint_every
        self.checkpoints = Checkpoints(scene, (solver, other), outputs.checkpoint if outputs and every else None,
                                       every, self.progress, self.diagnostics, opts.restart)
        self.handlers = (self.statistics, self.frames, self.snapshots, self.observations, self.diagnostics,
                         self.checkpoints)
        self.watch = (Runaway(scene, ppc, scene.method.name), Runaway(scene, ppc, scene.method.compare))
        self.blown = False  # whether a step blew up (and the run went on)
        self.written = self._written()  # every file or folder written, by what it holds
        # the file a stopped run leaves marked incomplete: not when it replaces a complete result, which stays
        self.stopped_file = self.rf.path if self.rf and not is_complete(self.rf.path) else None

    def _written(self) -> dict[str, Path]:
        """Every file or folder the run writes, by what it holds, where it lies once the run ends."""
        o = self.outputs
        where = {"statistics and diagnostics": self.rf and self.rf.path,
                 "frames": self.frames.writer and o.frames,
                 "openPMD snapshots": self.snapshots.directory and o.snapshots, "checkpoint": self.checkpoints.path,
                 "structure factor": self.spectrum_png, "time series": self.series_png,
                 "observables": self.observables_png}
        return {what: path for what, path in where.items() if path}

    def wall(self) -> float:
        """Seconds the run has taken, a restarted run's earlier part included."""
        return time.perf_counter() - self.wall0

    def advance(self, n: int) -> None:
        """Step ``n`` → ``n + 1`` of both solvers; their diagnostics kept; a NaN mass refused."""
        t0 = time.perf_counter()
        self.solver.step(n)
        t0 = self.clock.add("solver", t0)
        d = self.solver.diagnostics()
        blown = self.watch[0].check(d)
        if self.other:
            self.other.step(n)
            self.clock.add("compare", t0)
            od = self.other.diagnostics()
            blown = blown or self.watch[1].check(od, f" in {self.scene.method.compare} (run alongside)")
            d |= {f"compare_{k}": v for k, v in od.items() if k in COMPARED}
        self.diagnostics.append((n + 1) * self.scene.dt, d)
        if blown and (not self.blown or "NaN" in blown):  # said once; NaN always stops
            self.blew_up(n + 1, blown)

    def blew_up(self, step: int, what: str) -> None:
        """The first step that blew up: said in one line and marked in the run file (root attribute
        ``runaway``; ``/diagnostics`` attributes ``runaway_step`` and ``runaway_time``); the run
        stops (:class:`SimulationError`) unless ``runaway = "continue"`` and the values are finite."""
        t, sc = step * self.scene.dt, self.scene
        message = f"{what} at step {step} (t = {t:.4g}): the scheme is unstable at C = {sc.time.C}; lower C"
        if self.rf:
            self.diagnostics.flush(force=True)
            self.rf.annotate("runaway", message)
            self.rf.diag.attrs.update(runaway_step=step, runaway_time=t)
        if sc.time.runaway == "stop" or "NaN" in what:
            raise SimulationError(message)
        print(f"ti_dk: warning: {message} (runaway = continue: running on)", file=sys.stderr)
        self.blown = True

    def record(self, n: int) -> None:
        """After step ``n``: every handler that is due writes, its time counted to its part."""
        for handler in self.handlers:
            if handler.due(n):
                t0 = time.perf_counter()
                handler.write(n)
                self.clock.add(handler.part, t0)

    def progress(self, n: int) -> Progress:
        """What the run has produced by step ``n`` (a checkpoint's content, with the solver states)."""
        st = self.statistics
        return Progress(step=n, rows=st.rows, times=st.times, diag=self.diagnostics.diag, frames=self.frames.log,
                        series=self.observations.series, pooled=st.pooled_state(), timing=self.clock.parts,
                        wall=self.wall())

    def make_movie(self) -> None:
        """The MP4 of every frame."""
        if self.frames.writer:
            t0 = time.perf_counter()
            movie = self.frames.writer.movie(self.outputs.staged(self.outputs.movie))
            self.rf.annotate("movie_bytes", movie.stat().st_size)  # what tells a later run the movie is ours
            self.written["movie"] = self.outputs.movie
            self.clock.add("render", t0)

    def draw_structure_factor(self) -> None:
        """The last row's S(k) against its exact answer (:mod:`ti_dk.output.spectra`)."""
        st = self.statistics
        if self.spectrum_png and st.rows:
            from ..output.spectra import draw_structure_factor

            t0 = time.perf_counter()
            staged = self.outputs.staged(self.outputs.frames) / self.spectrum_png.name  # moved into place at the end
            draw_structure_factor(staged, self.scene, st.rows[-1], st.row_steps(self.scene.n_steps))
            self.clock.add("render", t0)

    def draw_series(self) -> None:
        """The run's series and its observables over time, mean ± SE over members (:mod:`ti_dk.output.series`)."""
        if not self.series_png:  # no output, or no frames
            return
        from ..output import series

        t0 = time.perf_counter()
        staged, records = self.outputs.staged(self.outputs.frames), self.series()
        series.draw_series(staged / self.series_png.name, self.scene, records, self.diagnostics.diag)
        if self.observables_png:
            series.draw_observables(staged / self.observables_png.name, self.scene, records)
        self.clock.add("render", t0)

    def series(self) -> dict[str, np.ndarray]:
        """The per-member records so far, as arrays (``Result.series``)."""
        return {k: np.asarray(v) for k, v in self.observations.series.items()}

    def finish(self, wall: float) -> Result:
        """Close the run file (marked complete) and return the result."""
        timing = self.clock.result(wall)
        regrids = list(self.solver.regrids)
        if self.rf:
            self.rf.write_table("regrid", regrids)
            if self.frames.writer:
                self.rf.write_table("frames", self.frames.table())
            self.rf.annotate("timing", timing)
            self.rf.close(wall)
        sc, st = self.scene, self.statistics
        return Result(scene=sc, times=np.array(st.times), cell_volume=sc.grid.cell_volume,
                      stats=stats_of(st.rows, sc.stats.histogram),
                      diagnostics={k: np.asarray(v) for k, v in self.diagnostics.diag.items()},
                      final_density=self.solver.density(), wall_time=wall, path=self.rf.path if self.rf else None,
                      regrids=regrids, timing=timing, rows=st.rows, written=self.written, series=self.series(),
                      frames=[self.outputs.frames / p.name for p in self.frames.files()], samples=st.samples)


class Runaway:
    """Whether a step blew up, from one solver's diagnostics after it (sums over the members):
    a NaN or infinite mass; a cell holding (in magnitude) more than :attr:`GROWTH` times any
    particle count the scene can hold, the whole initial content of a member or its reservoirs
    filling every cell; or, where the mass is conserved (not in the hybrid, whose regrids turn
    fractional SPDE content into whole particles), its changing by more than :attr:`CONSERVED` of
    itself beyond what the boundaries let in (measured below 1e-8 in f32 and f64)."""

    GROWTH, CONSERVED = 100.0, 1e-6

    def __init__(self, scene: Scene, ppc: np.ndarray, method: str | None):
        g, E = scene.grid, scene.method.ensemble
        reservoirs = max((r for sides in g.reservoir_ppc for r in sides), default=0.0) * math.prod(g.cells)
        self.most = max(float(np.sum(ppc)), reservoirs, 1.0)  # particles a member can hold
        self.vol, self.members, self.mass = g.cell_volume, E, None  # mass: after the step before
        self.conserved = method != "hybrid"

    def check(self, d: dict, where: str = "") -> str:
        """What blew up in this step (``""``: nothing)."""
        mass, before = d["mass"], self.mass
        if not math.isfinite(mass):
            return f"the density became NaN or infinite{where}"
        self.mass = mass
        cell = -d["min_density"] * self.vol if math.isfinite(d["min_density"]) else 0.0  # particles
        big, what = max((cell, "a cell"), (abs(mass) / self.members, "a member"))
        if big > self.GROWTH * self.most:
            return (f"the density blew up{where}: {big:.3g} particles in {what}, beyond {self.GROWTH:g} times any "
                    f"count it can hold ({self.most:.4g})")
        if before is not None and self.conserved:
            lost = mass - before - d["boundary_inflow"]
            if abs(lost) > self.CONSERVED * max(abs(before), abs(mass), self.members):
                return (f"the mass blew up{where}: it changed by {lost:.3g} particles in one step beyond the "
                        f"boundary inflow, where it is conserved to round-off")
        return ""


OVERDUE_SECONDS, OVERDUE_FACTOR = 60.0, 3.0  # a run past both says how far it is


class StepBar:
    """The progress bar of the steps; the first step, which compiles the step kernels, is timed as
    ``compile`` and left out of the rate and the ETA."""

    def __init__(self, scene: Scene, start: int, show: bool, clock: Clock, estimate: float = math.inf):
        self.label = f"{scene.name}/{scene.method.name}"
        self.start, self.total = start, scene.n_steps
        self.t0 = time.perf_counter()  # when this part of the run began
        self.overdue = max(OVERDUE_SECONDS, OVERDUE_FACTOR * estimate)  # said once when passed, from t0
        self.bar = tqdm(total=scene.n_steps, initial=start, disable=not show, unit="step",
                        desc=f"{self.label}: compiling", file=sys.stderr, mininterval=0.5)
        self.clock = clock  # where the first step's time moves to "compile"
        self.first = True  # no step done yet
        self.before: dict[str, float] = {}  # the parts' seconds before the first step
        self.t_first = 0.0  # when the first step began

    def __enter__(self) -> "StepBar":
        return self

    def __exit__(self, *exc) -> None:
        self.bar.close()

    def starting(self) -> None:
        """A step begins."""
        if self.first:
            self.t_first = time.perf_counter()
            self.before = self.clock.all()

    def stepped(self, step: int) -> None:
        """``step`` steps are done (the handlers included); a run far past its estimate says so once."""
        if not self.first:
            self.bar.update()
            elapsed = time.perf_counter() - self.t0
            if elapsed > self.overdue:
                self.overdue = math.inf
                left = elapsed / (step - self.start) * (self.total - step)
                self.bar.write(f"ti_dk: note: {elapsed / 60:.3g} min so far, more than {OVERDUE_FACTOR:g}x the "
                               f"estimate; {step:,} of {self.total:,} steps done, about {left / 60:.3g} min to go",
                               sys.stderr)
            return
        self.first = False
        self.clock.compiled(self.before, self.t_first)
        self.bar.set_description(self.label, refresh=False)
        self.bar.reset()  # restart the rate and ETA clock after compilation
        self.bar.initial = self.bar.n = self.bar.last_print_n = step
        self.bar.refresh()


def _frame_steps(scene: Scene, frames: bool, movie: bool) -> set[int]:
    """The steps that get a frame: the output steps (and step 0 in 2D/3D), plus evenly spaced ones
    for a movie (not for a stationary scene)."""
    steps = set(scene.output_steps) | ({0} if frames and scene.grid.dim > 1 else set())
    if movie and scene.stats.t_equil is None:
        steps |= {round(k * scene.n_steps / scene.output.movie_frames) for k in range(scene.output.movie_frames + 1)}
    return steps


def _frame_writer(outputs: Outputs, scene: Scene, other: Solver | None):
    """The frame writer of this scene: moment profiles in 1D, density panels in 2D and 3D."""
    from ..output.render import FrameWriter

    return FrameWriter(outputs.staged(outputs.frames), _renderer(scene, other))


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
    lines += [f"  {line}" for line in summary_lines(sc, result.series)]
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


def _close_quietly(ctl: Controller, error: str) -> None:
    """Mark the run file incomplete on the way out of a failed or stopped run, its diagnostics written
    up to the last step done; a second failure (the disk still full) must not hide the first."""
    try:
        ctl.diagnostics.flush(force=True)
    except (OSError, RuntimeError, ValueError):
        pass
    try:
        ctl.rf.close(ctl.wall(), error=error)
    except OSError:
        pass


def _renderer(scene: Scene, other: Solver | None):
    """What draws this scene's frames: moment profiles in 1D, density panels in 2D and 3D."""
    if scene.grid.dim == 1:
        from ..output.profiles import ProfileRenderer

        return ProfileRenderer(scene)
    from ..output.render import Renderer

    return Renderer.of(scene, compared=other is not None)
