"""The output handlers' schedules, the run clock's parts, and what a handler that is off writes."""
from pathlib import Path

import numpy as np

from ti_dk import load_scene
from ti_dk.control.checkpoint import Progress
from ti_dk.control.handlers import (TIMING_ORDER, Checkpoints, Clock, Diagnostics, Frames, Observations, Snapshots,
                                    Statistics)
from ti_dk.methods.solver import Solver


class Flat(Solver):
    """A solver that never changes: four particles per cell in every member."""

    def __init__(self, scene, timing=None):
        self.shape, self.vol = (scene.method.ensemble, *scene.grid.cells), scene.grid.cell_volume
        if timing is not None:
            self.timing = timing

    def density(self):
        return np.full(self.shape, 4.0 / self.vol)


def test_statistics_rows_at_the_output_steps_and_extra_rows_for_frames_only():
    scene = load_scene("void1d", ensemble=3, t_end=0.001, output_times=[0.0005])
    stats = Statistics(scene, Flat(scene), None, Progress(), extra_steps=(2,))
    out = scene.output_steps
    assert [n for n in range(scene.n_steps + 1) if stats.due(n)] == sorted({*out, 2})
    for n in (2, *out):
        stats.write(n)
    assert stats.row_at(2) is None and stats.row_at(out[-1])["n_samples"] == 3
    assert len(stats.rows) == len(out) and stats.times == [n * scene.dt for n in out]
    assert stats.pooled_state() is None


def test_stationary_statistics_pool_samples_into_one_row_at_the_end():
    scene = load_scene("equilibrium1d", ensemble=2, t_end=0.002, t_equil=0.001, sample_every=5)
    stats = Statistics(scene, Flat(scene), None, Progress())
    due = [n for n in range(scene.n_steps + 1) if stats.due(n)]
    n_eq = round(0.001 / scene.dt)
    assert due[0] == n_eq and due[-1] == scene.n_steps
    for n in due:
        stats.write(n)
    assert len(stats.rows) == 1 and stats.rows[0]["n_samples"] == 2 * len(range(n_eq, scene.n_steps + 1, 5))


def test_handlers_that_are_off_are_never_due():
    scene = load_scene("ellipse2d", cells=[8, 8], t_end=0.001, output_times=[0.0])
    solver = Flat(scene)
    stats = Statistics(scene, solver, None, Progress())
    diag = Diagnostics(None, {"time": []}, stats)
    off = [Frames(scene, solver, None, None, {0}, {"time": []}, stats), Snapshots(scene, solver, None), diag,
           Checkpoints(scene, (solver, None), None, 1, lambda n: Progress(step=n), diag)]
    assert not any(h.due(n) for h in off for n in range(scene.n_steps + 1))


def test_observations_are_due_at_step_0_every_sample_every_steps_and_the_last():
    scene = load_scene("void1d", t_end=0.001, sample_every=3, output_times=[], observables={"left": "x < 0.5"})
    obs = Observations(scene, Flat(scene), None, {})
    assert scene.n_steps % 3 and [n for n in range(scene.n_steps + 1) if obs.due(n)] == [
        *range(0, scene.n_steps, 3), scene.n_steps]
    plain = load_scene("void1d", t_end=0.1, output_times=[])  # no observables: about SERIES_POINTS records of the run's own series
    assert plain.observe_every == plain.n_steps // 200 > 1


def test_checkpoints_fall_between_the_first_and_the_last_step():
    scene = load_scene("void1d", t_end=0.001)
    ck = Checkpoints(scene, (None, None), Path("unused.h5"), 4, lambda n: Progress(step=n), None)
    assert [n for n in range(scene.n_steps + 1) if ck.due(n)] == list(range(4, scene.n_steps, 4))


def test_the_clock_orders_the_parts_and_moves_the_first_step_into_compile():
    scene = load_scene("void1d")
    solver = Flat(scene, timing={"spde": 0.0, "particles": 0.0, "regrid": 0.0})
    clock = Clock({}, solver)
    before = clock.all()
    clock.parts["solver"] = 1.0
    solver.timing["spde"] = 2.0
    clock.compiled(before, t0=0.0)  # everything since `before` was compilation
    assert clock.parts["solver"] == 0.0 and solver.timing["spde"] == 0.0 and clock.parts["compile"] > 0
    timing = clock.result(wall=clock.parts["compile"] + 1.0)
    assert "solver" not in timing  # the solver's own parts replace it
    parts = [k for k in timing if k not in ("other", "total")]
    assert parts == [k for k in TIMING_ORDER if k in parts]
    assert timing["other"] > 0 and np.isclose(sum(v for k, v in timing.items() if k != "total"), timing["total"])
