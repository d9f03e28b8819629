"""A run's output handlers, each with its own schedule: ``due(step)`` says whether it writes after
that step, ``write(step)`` writes, and ``part`` names the part of the run its time counts to.

The run controller (:class:`ti_dk.control.controller.Controller`) asks them in order after every step:
:class:`Statistics`, :class:`Frames`, :class:`Snapshots`, :class:`Observations`, :class:`Diagnostics`,
:class:`Checkpoints`.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .checkpoint import Progress, write_checkpoint
from ..scene import observables
from ..scene.schema import Scene
from ..output.files import RunFile, frame_file, pack_ids, write_openpmd
from ..methods.records import MemberSums
from ..methods.solver import Solver
from ..core.stats import CellStats

FLUSH_SECONDS = 5.0  # per-step diagnostics reach the file at least this often (and at every checkpoint)
TIMING_ORDER = ("setup", "compile", "regrid", "spde", "particles", "solver", "compare", "statistics", "render", "io")


class Clock:
    """Seconds per part of a run (:data:`TIMING_ORDER`); a solver that splits its step (the hybrid:
    spde, particles, regrid) keeps its own parts in ``solver.timing``."""

    def __init__(self, parts: dict[str, float], solver: Solver):
        self.parts = parts  # seconds per part of the run, restored from a checkpoint or empty
        self.solver = solver  # whose ``timing`` holds the parts of its step
        for part in ("setup", "compile", "statistics", "render", "io"):
            parts.setdefault(part, 0.0)

    def add(self, part: str, t0: float) -> float:
        """Count the time since ``t0`` to ``part``; return the time now."""
        t1 = time.perf_counter()
        self.parts[part] = self.parts.get(part, 0.0) + t1 - t0
        return t1

    def all(self) -> dict[str, float]:
        """Seconds spent so far in each part of the run, the solver's own parts included."""
        return {**self.parts, **self.solver.timing}

    def compiled(self, before: dict[str, float], t0: float) -> None:
        """Move what every part took since ``before`` (the first step, which compiles the step
        kernels) into ``compile``."""
        for k, v in self.all().items():
            (self.solver.timing if k in self.solver.timing else self.parts)[k] -= v - before.get(k, 0.0)
        self.add("compile", t0)

    def result(self, wall: float) -> dict[str, float]:
        """The parts in step order, ``other`` (progress bar, diagnostics, closing files) and ``total``."""
        timing = self.all()
        if self.solver.timing:  # its own parts replace "solver"
            timing.pop("solver", None)
        timing = {k: timing[k] for k in TIMING_ORDER if k in timing}
        timing["other"] = max(0.0, wall - sum(timing.values()))  # wall: a restarted run's earlier part included
        timing["total"] = wall
        return timing


class Statistics:
    """Statistics rows over the ensemble at ``scene.output_steps`` (and at ``extra_steps``, rows only
    drawn by 1D frames); a stationary scene pools every ``sample_every``-th step after ``t_equil``
    into one row at the end. With ``stats.structure_factor`` the rows carry S(k)
    (:mod:`ti_dk.core.spectra`). With ``keep``, ``samples`` holds each kept row's densities,
    ``(samples per member, members, *cells)`` (a stationary row pools several steps)."""

    part = "statistics"

    def __init__(self, scene: Scene, solver: Solver, rf: RunFile | None, prog: Progress, extra_steps=(),
                 keep: bool = False):
        self.scene, self.solver, self.rf = scene, solver, rf
        self.samples: list | None = [] if keep else None  # per kept row, its densities (with keep)
        self.taken: list = []  # the densities behind the row being taken (with keep)
        self.rows, self.times = prog.rows, prog.times  # the rows at output steps so far, and their times
        self.outputs = set(scene.output_steps)  # steps whose row is kept and written
        self.extra = set(extra_steps)  # steps whose row only draws a frame
        self.stationary = scene.stats.t_equil is not None
        self.n_equil = round(scene.stats.t_equil / scene.dt) if self.stationary else 0  # first pooled step
        # stationary runs: the pooled samples
        self.pooled = self._cell_stats()
        if prog.pooled:
            self.pooled.load_state(prog.pooled)
        self.latest: tuple[int | None, dict | None] = (None, None)  # (step, row) of the last row taken
        if rf:  # a restarted run writes what the checkpoint holds first: the file ends up the same
            rf.write_rows(self.times, self.rows)

    def due(self, n: int) -> bool:
        """Whether step ``n`` takes a row: an output or frame step; stationary, a pooled sample or the last step."""
        if self.stationary:
            return self._sampled(n) or n == self.scene.n_steps
        return n in self.outputs or n in self.extra

    def _sampled(self, n: int) -> bool:
        return n >= self.n_equil and (n - self.n_equil) % self.scene.stats.sample_every == 0

    def write(self, n: int) -> None:
        """Take step ``n``'s row (stationary: pool its sample, the row at the last step); at an
        output step keep it and write it to the run file."""
        sc = self.scene
        if self.stationary:
            if self._sampled(n):
                self.pooled.add(self._density())
            row = self.pooled.row() if n == sc.n_steps else None
        else:
            self.taken = []
            cs = self._cell_stats()
            cs.add(self._density())
            row = cs.row()
        self.latest = (n, row)
        if row is not None and n in self.outputs:
            if self.samples is not None:
                self.samples.append(np.stack(self.taken))
            self.rows.append(row)
            self.times.append(n * sc.dt)
            if self.rf:
                self.rf.write_row(n * sc.dt, row)

    def _density(self):
        """Every member's density now (kept with ``keep``)."""
        rho = self.solver.density()
        if self.samples is not None:
            self.taken.append(rho.copy())
        return rho

    def _cell_stats(self) -> CellStats:
        sc = self.scene
        return CellStats(sc.grid.cells, sc.grid.cell_volume, sc.stats.histogram, sc.stats.structure_factor)

    def row_steps(self, n: int) -> int | range:
        """The steps whose samples make the row of step ``n``: ``n``, or those pooled up to it."""
        if not self.stationary:
            return n
        return range(self.n_equil, n + 1, self.scene.stats.sample_every)

    def row_at(self, n: int) -> dict | None:
        """The row taken at step ``n``, if one was."""
        step, row = self.latest
        return row if step == n else None

    def pooled_state(self) -> dict | None:
        """What a checkpoint keeps of the pooled accumulator (stationary scenes)."""
        return self.pooled.state() if self.stationary else None


class Observations:
    """Per member, every ``scene.observe_every`` steps, step 0 and the last: its mass and negative
    cells, for a solver with a particle region the particles in it and its cells, and the particle
    count of each region of ``[observables]`` (:mod:`ti_dk.scene.observables`), summed on the
    device (:class:`~ti_dk.methods.records.MemberSums`: one small read a record, not the
    densities). ``series``: name → one entry per record (restored from a checkpoint or empty);
    written to the run file by :meth:`flush` (``/series``, ``/observables``)."""

    part = "statistics"

    def __init__(self, scene: Scene, solver: Solver, rf: RunFile | None, series: dict):
        self.scene, self.solver, self.rf = scene, solver, rf
        self.series = series  # "time" and each series' per-member values, per record
        self.masks = observables.masks(scene)  # each observable's cells
        self.sums: MemberSums | None = None  # made at the first record
        self.done = 0  # records in the file

    def due(self, n: int) -> bool:
        """Every ``observe_every`` steps, step 0 and the last."""
        return n % self.scene.observe_every == 0 or n == self.scene.n_steps

    def write(self, n: int) -> None:
        """Record step ``n`` per member: mass, negative cells, the region's particles and cells, each
        observable's count."""
        if self.sums is None:
            self.sums = MemberSums(self.solver.grid, self.solver.ensemble, self.masks)
        record = {"time": n * self.scene.dt} | self.sums.record(*self.solver.content())
        for k, v in record.items():
            self.series.setdefault(k, []).append(v)

    def flush(self) -> None:
        """Write the records not yet in the run file."""
        n = len(self.series.get("time", ()))
        if self.rf is not None and n > self.done:
            self.rf.write_series({k: v[self.done:] for k, v in self.series.items()}, tuple(self.masks))
            self.done = n


class Diagnostics:
    """Per-step diagnostics on their way to the run file (and the :class:`Observations` records):
    written with every statistics row, at every checkpoint and at least every ``FLUSH_SECONDS``,
    so a killed run keeps them up to then."""

    part = "io"

    def __init__(self, rf: RunFile | None, diag: dict, statistics: Statistics,
                 observations: Observations | None = None):
        self.rf, self.diag = rf, diag  # diag: per step, every key the solvers report (restored or empty)
        self.statistics = statistics  # whose rows force a flush
        self.observations = observations  # whose records are flushed with the diagnostics
        self.done, self.last = 0, time.monotonic()  # steps in the file; when they were written
        self.flush(force=True)

    def append(self, t: float, d: dict) -> None:
        """The diagnostics of the step that ended at time ``t``."""
        self.diag["time"].append(t)
        for k, v in d.items():
            self.diag.setdefault(k, []).append(v)

    def due(self, n: int) -> bool:
        """Every step of a run with a run file (:meth:`flush` decides whether it writes)."""
        return self.rf is not None

    def write(self, n: int) -> None:
        """Flush: at once where step ``n`` took a statistics row, else when :meth:`flush` is due."""
        self.flush(force=self.statistics.row_at(n) is not None)

    def flush(self, force: bool = False) -> None:
        """Write the steps not yet in the run file, and the observations' records, with ``force`` or
        when ``FLUSH_SECONDS`` have passed since the last write."""
        if self.rf is None or not (force or time.monotonic() - self.last > FLUSH_SECONDS):
            return
        n = len(self.diag["time"])
        if n > self.done:
            self.rf.write_diagnostics({k: v[self.done:] for k, v in self.diag.items()})
        if self.observations is not None:
            self.observations.flush()
        self.done, self.last = n, time.monotonic()


class Frames:
    """PNG frames at ``steps``: member 0's density of each method in 2D/3D, the ensemble's moment
    profiles in 1D (from the :class:`Statistics` row of that step); ``writer`` None writes none."""

    part = "render"

    def __init__(self, scene: Scene, solver: Solver, other: Solver | None, writer, steps: set, log: dict,
                 statistics: Statistics):
        self.scene, self.solver, self.other = scene, solver, other
        self.writer = writer  # ti_dk.output.render.FrameWriter, or None
        self.steps = steps  # the steps that get a frame
        self.log = log  # per frame: time and negative cells (restored from a checkpoint or empty)
        self.statistics = statistics  # whose rows 1D frames draw
        if writer is not None:
            writer.files = [frame_file(writer.dir, k) for k in range(len(log["time"]))]

    def due(self, n: int) -> bool:
        """Whether step ``n`` gets a frame."""
        return self.writer is not None and n in self.steps

    def write(self, n: int) -> None:
        """Draw step ``n``'s frame; log its time and negative cells."""
        t = n * self.scene.dt
        self.log["time"].append(t)
        if self.scene.grid.dim == 1:
            region = self.solver.region()
            self.writer.write(t, self.statistics.row_at(n), None if region is None else region.mean(axis=0))
            self.log["negative_cells"].append(int((self.solver.density() < 0).sum()))  # all members
            return
        panels = self.panels()
        self.writer.write(t, panels)
        self.log["negative_cells"].append(int((panels[0].ppc < 0).sum()))
        if self.other:
            self.log.setdefault("compare_negative_cells", []).append(int((panels[1].ppc < 0).sum()))

    def panels(self) -> list:
        """Member 0 of each method as a frame panel, in particles per cell."""
        from ..output.render import Panel

        sc, boxes = self.scene, self.solver.boxes
        panels = [Panel(sc.method.name, self.solver.density()[0] * sc.grid.cell_volume, boxes[0] if boxes else None,
                        tiles=sc.method.name == "hybrid" and sc.hybrid.region == "tiles")]
        if self.other:
            panels.append(Panel(sc.method.compare, self.other.density()[0] * sc.grid.cell_volume))
        return panels

    def files(self) -> list[Path]:
        """The frame files, those of the run before a restart included."""
        return list(self.writer.files) if self.writer else []

    def table(self) -> list[dict]:
        """One record per frame (the run file's ``/frames``)."""
        return [dict(zip(self.log, v)) for v in zip(*self.log.values())]


class Snapshots:
    """openPMD snapshots of member 0 at the output steps (:meth:`ti_dk.methods.solver.Solver.snapshot`);
    ``directory`` None writes none."""

    part = "io"

    def __init__(self, scene: Scene, solver: Solver, directory: Path | None):
        self.scene, self.solver, self.directory = scene, solver, directory
        self.steps = set(scene.output_steps)  # the steps that get a snapshot

    def due(self, n: int) -> bool:
        """Whether step ``n`` is an output step (and snapshots are written)."""
        return self.directory is not None and n in self.steps

    def write(self, n: int) -> None:
        """Member 0 at step ``n`` as an openPMD snapshot."""
        s, sc = self.solver.snapshot(0), self.scene
        write_openpmd(self.directory, n, n * sc.dt, sc.dt, sc.grid, s.density, s.region, s.positions,
                      None if s.pid is None else pack_ids(s.pid), s.boxes, (sc.output.length_si, sc.output.diffusion_si))


class Checkpoints:
    """A checkpoint every ``every`` steps (never after the last step), written atomically over the
    previous one; ``path`` None writes none. ``latest``: the checkpoint a stopped run resumes from."""

    part = "io"

    def __init__(self, scene: Scene, solvers: tuple[Solver, Solver | None], path: Path | None, every: int,
                 progress: Callable[[int], Progress], diagnostics: Diagnostics, latest: Path | None = None):
        self.scene, self.solvers, self.path, self.every = scene, solvers, path, every
        self.progress = progress  # what the run has produced by a step
        self.diagnostics = diagnostics  # flushed with every checkpoint
        self.latest = latest  # the newest checkpoint on disk (the one restarted from, at first)

    def due(self, n: int) -> bool:
        """Every ``every`` steps, neither at step 0 nor at the last."""
        return self.path is not None and 0 < n < self.scene.n_steps and n % self.every == 0

    def write(self, n: int) -> None:
        """The diagnostics flushed, then the checkpoint of step ``n`` written over the last one."""
        # diagnostics first: a run killed right after the checkpoint lands must find them in the run
        # file up to its step (test_a_killed_run_keeps_its_diagnostics_up_to_the_last_flush)
        self.diagnostics.flush(force=True)
        write_checkpoint(self.path, self.scene, *self.solvers, self.progress(n))
        self.latest = self.path
