"""The run controller: result shapes and units, stationary pooling, the HDF5 record, failures."""
import json
import math

import h5py
import numpy as np
import pytest

import ti_dk
from ti_dk import SimulationError, load_scene, run
from ti_dk.core import theory

from ..helpers import ROOT


def test_result_and_file(tmp_path):
    scene = load_scene("void1d", ensemble=50, t_end=0.001, output_times=[0.0, 0.0005])
    res = run(scene, out=tmp_path)
    assert res.times.tolist() == pytest.approx([0.0, 0.0005, 0.001])
    assert res.stats.mean.shape == (3, 100) and res.stats.kurtosis.shape == (3, 100)
    # number-density units: the initial mean is 20 particles per cell / V_c = 2000
    assert res.stats.mean[0].max() == pytest.approx(2000.0)
    assert res.diagnostics["mass"].shape == (scene.n_steps,)
    with h5py.File(res.path) as f:
        assert f.attrs["complete"]
        assert json.loads(f.attrs["scene"])["method"]["ensemble"] == 50
        assert f.attrs["wall_time"] > 0
        assert np.array_equal(f["stats/mean"][:], res.stats.mean)
        assert f["stats/time"].shape == (3,)
        assert np.allclose(f["diagnostics/mass"][:], 1000 * 50)  # 50 cells x 20 particles x 50 members


def test_stationary_pooling_counts_samples():
    scene = load_scene("equilibrium1d", method="gaussian", ensemble=40, ppc=5, C=0.1, t_end=0.02, t_equil=0.01,
                       sample_every=10)
    res = run(scene)
    n_eq = round(0.01 / scene.dt)
    samples = len(range(n_eq, scene.n_steps + 1, 10))
    assert res.stats.n_samples.tolist() == [samples * 40]
    assert res.times.tolist() == pytest.approx([scene.n_steps * scene.dt])
    # pooled variance after 1000 steps: near the stationary linear-scheme value (loose: time samples correlate)
    var = res.stats.variance[0].mean() * res.cell_volume**2
    assert var == pytest.approx(theory.linear_scheme_variance((100,), (0.1,), 5.0), rel=0.08)
    assert res.stats.histogram.shape == (1, 100, 41)
    assert res.stats.histogram[0].sum() == samples * 40 * 100  # every sample falls in [-10, 30] particles


def test_unstable_run_stops_with_a_clear_error(tmp_path):
    scene = load_scene("void1d", method="gaussian", C=1.2, allow_unstable=True, ensemble=1, t_end=0.5)
    with pytest.raises(SimulationError, match="unstable at C = 1.2; lower C"):
        run(scene, out=tmp_path)
    with h5py.File(tmp_path / "void1d_gaussian.h5") as f:
        assert not f.attrs["complete"] and "unstable" in f.attrs["error"]


def test_restart_is_bitwise_identical(tmp_path):
    scene = load_scene("ellipse2d", cells=[24, 24], t_end=0.003, regrid_interval=4,
                       output_times=[0.0, 0.001, 0.002], sample_every=3,
                       observables={"left": "x < 0.5", "ring": "0.1**2 < (x-0.5)**2 + (y-0.5)**2 < 0.3**2"})
    whole = run(scene, out=tmp_path / "whole", snapshots=False)
    run(scene, out=tmp_path / "first", snapshots=False, checkpoint_every=20)
    ckpt = tmp_path / "first" / "ellipse2d_hybrid_checkpoint.h5"
    with h5py.File(ckpt) as f:
        step = int(f.attrs["step"])
    assert 0 < step < scene.n_steps and step % 20 == 0
    resumed = run(scene, out=tmp_path / "second", snapshots=False, restart=ckpt)
    assert np.array_equal(whole.final_density, resumed.final_density)
    for k in ("mean", "variance", "skewness", "kurtosis"):
        assert np.array_equal(getattr(whole.stats, k), getattr(resumed.stats, k), equal_nan=True)
    assert np.array_equal(whole.diagnostics["negative_cells"], resumed.diagnostics["negative_cells"])
    assert [r["step"] for r in whole.regrids] == [r["step"] for r in resumed.regrids]
    with h5py.File(whole.path) as a, h5py.File(resumed.path) as b:
        assert np.array_equal(a["stats/mean"][:], b["stats/mean"][:])
        assert np.array_equal(a["frames/compare_negative_cells"][:], b["frames/compare_negative_cells"][:])
        for k in ("observables/time", "observables/left", "observables/ring", "series/mass", "series/particles",
                  "series/region_cells", "series/negative_cells"):  # every record, those before the checkpoint too
            assert a[k].shape[0] == len(range(0, scene.n_steps, 3)) + 1 and np.array_equal(a[k][:], b[k][:]), k
        assert b.attrs["complete"]
    assert whole.series.keys() == resumed.series.keys()
    assert all(np.array_equal(whole.series[k], resumed.series[k]) for k in whole.series)
    assert [p.name for p in whole.frames] == [p.name for p in resumed.frames]
    assert min(resumed.timing.values()) >= 0 and resumed.timing["other"] < resumed.timing["total"]


def test_restart_refuses_other_settings(tmp_path):
    scene = load_scene("void1d", ensemble=4, t_end=0.0005)
    run(scene, out=tmp_path, checkpoint_every=10)
    with pytest.raises(ti_dk.ConfigError, match=r"other settings \(method.ensemble: checkpoint 4, now 5\)"):
        run(load_scene("void1d", ensemble=5, t_end=0.0005), restart=tmp_path / "void1d_fv_checkpoint.h5")


def test_a_stopped_run_keeps_the_diagnostics_of_every_step_done(tmp_path, monkeypatch):
    """Stopped at step 7, between flushes (no checkpoint, no row there): all 7 steps in the file."""
    import os
    import signal

    from ti_dk.control import handlers
    from ti_dk.control.signals import Stopped, stop_on_signals

    append = handlers.Diagnostics.append

    def signal_at_7(self, t, d):
        append(self, t, d)
        if len(self.diag["time"]) == 7:
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(handlers.Diagnostics, "append", signal_at_7)
    scene = load_scene("void1d", ensemble=2, cells=[16], t_end=0.004, output_times=[0.0])
    assert scene.n_steps > 7
    with stop_on_signals(), pytest.raises(Stopped, match="stopped by SIGINT at step 7 of"):
        run(scene, out=tmp_path)
    with h5py.File(tmp_path / "void1d_fv.h5") as f:
        assert not f.attrs["complete"] and "SIGINT" in f.attrs["error"]
        assert f["diagnostics/time"].shape == (7,) and f["diagnostics/mass"].shape == (7,)


def test_a_run_far_past_its_estimate_says_so_once(monkeypatch, capsys):
    from ti_dk.control import controller
    from ti_dk.control.handlers import Clock

    monkeypatch.setattr(controller, "OVERDUE_SECONDS", 0.0)
    scene = load_scene("void1d", ensemble=2, t_end=0.0005)
    bar = controller.StepBar(scene, 0, False, Clock({}, type("S", (), {"timing": {}})()), estimate=0.0)
    for n in range(1, 6):
        bar.starting()
        bar.stepped(n)
    err = capsys.readouterr().err
    assert err.count("ti_dk: note: ") == 1 and "more than 3x the estimate; 2 of 80 steps done" in err, err


# -- the extremes: each runs correctly or is refused with a message, never a silent NaN ------
def _steps(scene, steps, check=None):
    from ti_dk.control.registry import make_solver

    s = make_solver(scene, scene.initial_ppc)
    mass = [s.diagnostics()["mass"] if scene.method.name != "particle" else None]
    for n in range(steps):
        s.step(n)
        d = s.diagnostics()
        assert np.isfinite(d["mass"]) and np.all(np.isfinite(s.density()))
        mass.append(d["mass"])
        if check:
            check(s)
    return s, np.array(mass[1:])


def test_time_step_at_below_and_above_the_limit():
    with pytest.raises(ti_dk.ConfigError, match="stability limit"):
        load_scene("equilibrium1d", C=1.0)
    s, mass = _steps(load_scene("equilibrium1d", C=0.95, ppc=20, ensemble=4, t_equil=None, histogram=None), 3000)
    assert np.allclose(mass, mass[0], rtol=1e-12)
    with pytest.raises(SimulationError, match="unstable at C = 1.05; lower C"):
        run(load_scene("equilibrium1d", C=1.05, allow_unstable=True, ppc=20, ensemble=4, t_equil=None,
                       histogram=None, t_end=1.0))


@pytest.mark.parametrize("method", ["fv", "gaussian", "particle", "hybrid"])
def test_no_particles_at_all(method):
    s, mass = _steps(load_scene("void1d", method=method, ppc=0, ensemble=3), 50)
    assert np.all(s.density() == 0)
    if method == "hybrid":
        assert s.region().all()  # everything is below the threshold: one domain-wide region


def test_a_single_particle():
    res = run(load_scene("equilibrium1d", method="particle", particle_init="exact_uniform", ppc=0.01,
                         ensemble=50, t_equil=None, histogram=None, t_end=0.002))
    assert np.all(res.diagnostics["mass"] == 50)
    counts = res.final_density * res.cell_volume
    assert np.all(counts.sum(axis=1) == 1) and set(np.unique(counts)) == {0.0, 1.0}
    s, mass = _steps(load_scene("equilibrium1d", method="hybrid", ppc=0.01, ensemble=20, t_equil=None,
                                histogram=None), 100)
    assert s.region().all() and np.allclose(mass, mass[0]) and (s.density() >= 0).all()


def test_a_million_particles_per_cell():
    for method in ("fv", "gaussian", "hybrid"):
        s, mass = _steps(load_scene("equilibrium1d", method=method, ppc=1e6, ensemble=2, t_equil=None,
                                    histogram=None), 200)
        rel = s.density() * s.grid.cell_volume / 1e6 - 1
        assert 1e-5 < np.abs(rel).max() < 1e-2 and np.allclose(mass, mass[0], rtol=1e-12)
    with pytest.raises(ti_dk.ConfigError, match="GiB"):  # refused before anything is allocated
        load_scene("equilibrium1d", method="particle", ppc=1e6, ensemble=100)


@pytest.mark.parametrize("region", ["one cell", "whole domain", "on the periodic seam", "on a Neumann wall"])
def test_extreme_particle_regions_conserve(region):
    boundary = [["neumann", "neumann"], "periodic"] if region == "on a Neumann wall" else "periodic"
    scene = load_scene("equilibrium1d", method="hybrid", cells=[10, 8], lengths=[1.0, 2.0], ppc=4,
                       regrid_interval=0, threshold=1, boundary=boundary, ensemble=2, t_equil=None, histogram=None)
    from ti_dk.control.registry import make_solver

    s = make_solver(scene, scene.initial_ppc)
    m = np.zeros((10, 8), dtype=bool)
    if region == "one cell":
        m[4, 3] = True
    elif region == "whole domain":
        m[:] = True
    elif region == "on the periodic seam":
        m[[0, -1], :] = True
        m[:, [0, -1]] = True
    else:
        m[0, 2:6] = True
    s.set_region(m[None], 0)
    mass = [s.diagnostics()["mass"]]
    for n in range(100):
        s.step(n)
        mass.append(s.diagnostics()["mass"])
        assert (s.density()[s.region()] >= 0).all()
    assert np.allclose(mass, mass[0], rtol=1e-12)


@pytest.mark.parametrize("method", ["fv", "gaussian", "particle", "hybrid"])
def test_two_cells_per_axis(method):
    res = run(load_scene("ellipse2d", method=method, cells=[2, 2], compare="none", t_end=0.05))  # 3 steps
    assert np.all(np.isfinite(res.final_density))
    if method != "particle":
        assert np.allclose(res.diagnostics["mass"], res.diagnostics["mass"][0], rtol=1e-12)


@pytest.mark.slow  # ~30 s on a slow 2-core box; in CI, which has the time
def test_a_hundred_thousand_steps():
    """Mass drift over 10^5 steps, read every 10th step; the density is checked once at the end (a
    NaN or inf, once made, stays, and makes the mass NaN). Reading the density at every step made
    this test 130 s on a 2.45 GHz core, nearly all of it the reads."""
    from ti_dk.control.registry import make_solver

    scene = load_scene("equilibrium1d", ppc=50, cells=[20], C=0.25, ensemble=2, t_equil=None, histogram=None)
    s = make_solver(scene, scene.initial_ppc)
    mass = []
    for n in range(100_000):
        s.step(n)
        if n % 10 == 0:
            mass.append(s.diagnostics()["mass"])
    mass = np.array(mass)
    drift = np.abs(mass / mass[0] - 1).max()
    assert drift < 1e-11, drift
    assert np.all(np.isfinite(s.density()))


def test_summary_names_every_file_every_method_and_the_time_in_step_order(tmp_path):
    from ti_dk.control.handlers import TIMING_ORDER
    from ti_dk.control.controller import summary

    scene = load_scene("ellipse2d", cells=[16, 16], t_end=0.001, output_times=[0.0, 0.001])
    res = run(scene, out=tmp_path, movie=True, checkpoint_every=2, progress=False)
    text = summary(res)
    assert set(res.written) == {"statistics and diagnostics", "frames", "openPMD snapshots", "checkpoint", "movie",
                                "time series"}
    for path in res.written.values():
        assert path.exists() and str(path) in text
    neg = res.diagnostics["compare_negative_cells"]
    assert f"fv (run alongside): negative cells {int(neg[-1]):,} at the end, at most {int(neg.max()):,}" in text
    assert "hybrid: negative cells" in text and " regrids" in text
    parts = [k for k in res.timing if k != "total"]
    assert parts == [k for k in (*TIMING_ORDER, "other") if k in parts]  # in step order
    assert {"setup", "compile", "regrid", "spde", "particles", "compare", "render", "other"} <= set(parts)
    assert np.isclose(sum(res.timing[k] for k in parts), res.timing["total"])
    assert res.timing["other"] > -1e-9 and res.timing["compile"] > 0
    time_line = next(ln for ln in text.splitlines() if ln.startswith("time: "))
    assert time_line.index("compile (first step)") < time_line.index("spde") < time_line.index("render")


def test_summary_of_a_fixed_region_ensemble_speaks_per_member(tmp_path):
    from ti_dk.control.controller import summary

    res = run(load_scene("void1d", method="hybrid", ensemble=8, cells=[40], t_end=0.0005, output_times=[],
                         observables={"void": "0.3 < x < 0.7"}), out=tmp_path, progress=False)
    text = summary(res)
    assert "8 members" in text and "particles per member" in text and "(all members)" in text
    assert "fixed at the start: 22 cells per member" in text and "regrids" not in text
    assert str(tmp_path / "void1d_hybrid_frames") in text
    void = res.series["void"][-1]  # the void's particles in each member at the end
    assert void.mean() > 0 and f"void {void.mean():,.6g} ± {void.std(ddof=1) / np.sqrt(8):,.2g}" in text
    assert f"observables at t = {res.series['time'][-1]:.4g} (particles, mean ± SE over 8 members)" in text
    for what in ("time series", "observables"):
        assert f"{res.written[what]}  ({what})" in text and res.written[what].stat().st_size > 0


# -- seeds: the whole unsigned 64-bit range works; seeds below 2**31 keep their streams ----------
def test_seed_key_keeps_small_seeds_and_covers_64_bits():
    from ti_dk.core.rng import seed_key

    assert seed_key(5) == (5, 0) and seed_key(2**31 - 1) == (2**31 - 1, 0)
    for seed in (2**31, 2**32, 2**63, 2**64 - 1):
        lo, hi = seed_key(seed)
        assert -(2**31) <= lo < 2**31 and -(2**31) <= hi < 2**31  # fits Taichi's i32 literals
        assert (lo % 2**32) | (hi % 2**32) << 32 == seed  # the same bits


@pytest.mark.parametrize("method", ["fv", "particle", "hybrid"])
def test_large_seeds_run_and_differ(method):
    finals = []
    for seed in (2**31, 2**64 - 1):
        res = run(load_scene("void1d", method=method, seed=seed, ensemble=2, cells=[20], t_end=0.0005))
        assert np.isfinite(res.final_density).all()
        finals.append(res.final_density)
    assert not np.array_equal(*finals)


def test_a_run_off_taichis_thread_or_beside_another_is_refused(monkeypatch):
    """Taichi runs on the thread that started it, one run at a time: anything else is a clear error,
    not a crashed process."""
    import threading

    from ti_dk.control.controller import Controller

    scene = load_scene("void1d", cells=[8], t_end=0.001, output_times=[0.001])
    first = run(scene)  # Taichi started on this thread, if not before
    raised = []

    def off_thread():
        try:
            run(scene)
        except SimulationError as exc:
            raised.append(str(exc))

    t = threading.Thread(target=off_thread)
    t.start()
    t.join()
    assert raised and raised[0].startswith("Taichi was started on another thread"), raised
    advance = Controller.advance

    def nested(self, n):  # a second run while the first one steps
        with pytest.raises(SimulationError, match="another ti_dk.run is going in this process"):
            run(scene)
        advance(self, n)

    monkeypatch.setattr(Controller, "advance", nested)
    assert np.array_equal(run(scene).final_density, first.final_density)  # and the first goes on unharmed
    monkeypatch.undo()
    run(scene)  # the lock is released after each run


@pytest.mark.parametrize("method, C", [("fv", 1.5), ("gaussian", 3.0)])
def test_a_run_that_blows_up_to_finite_values_stops_says_where_and_marks_its_file(tmp_path, method, C):
    """It ended with exit 0 and -7.2e163 particles; now the first step past any particle count stops it."""
    scene = load_scene("void1d", method=method, cells=[8], t_end=14, C=C, allow_unstable=True, ensemble=1)
    with pytest.raises(SimulationError, match=r"^the density blew up: .* particles in a cell, beyond 100 times any "
                       rf"count it can hold \(80\) at step (\d+) \(t = .*\): the scheme is unstable at C = {C}; "
                       "lower C$") as err:
        run(scene, out=tmp_path)
    step = int(err.value.args[0].split(" at step ")[1].split()[0])
    assert step < 50  # caught while finite, long before the values overflow (step 400 reached 1e115)
    with h5py.File(tmp_path / f"void1d_{method}.h5") as f:
        assert not f.attrs["complete"] and f.attrs["runaway"] == f.attrs["error"] == str(err.value)
        assert f["diagnostics"].attrs["runaway_step"] == step == len(f["diagnostics/mass"])
        assert f["diagnostics"].attrs["runaway_time"] == pytest.approx(step * scene.dt)
        assert np.all(np.isfinite(f["diagnostics/mass"][:]))


def test_a_run_asked_to_go_on_past_a_blow_up_says_it_once_and_marks_its_file(tmp_path, capsys):
    scene = load_scene("void1d", cells=[8], t_end=0.5, C=1.5, allow_unstable=True, ensemble=2, runaway="continue")
    res = run(scene, out=tmp_path)
    err = capsys.readouterr().err
    assert err.count("the density blew up") == 1 and "(runaway = continue: running on)" in err
    with h5py.File(res.path) as f:
        assert f.attrs["complete"] and "the density blew up" in f.attrs["runaway"]
        assert 0 < f["diagnostics"].attrs["runaway_step"] < scene.n_steps == len(f["diagnostics/mass"])


def test_the_mass_watch_sees_a_change_beyond_round_off_where_mass_is_conserved():
    from ti_dk.control.controller import Runaway

    scene = load_scene("void1d", cells=[8], ensemble=2)
    d = {"mass": 160.0, "min_density": 0.0, "boundary_inflow": 0.0}
    for method, said in (("fv", "the mass blew up: it changed by 0.001 particles"), ("hybrid", "")):
        watch = Runaway(scene, scene.initial_ppc, method)
        assert watch.check(d) == watch.check(d) == ""
        assert watch.check(d | {"mass": 160.001}).startswith(said)
    assert Runaway(scene, scene.initial_ppc, "fv").check(d | {"mass": math.nan}).startswith("the density became NaN")


@pytest.mark.parametrize("bad", [None, {"init": "void"}, 3, ["void1d"]])
def test_run_takes_a_scene_or_its_name_and_refuses_anything_else(bad, tmp_path):
    with pytest.raises(TypeError, match=r"run takes a Scene \(from ti_dk.load_scene\) or a scene name or .toml path, "
                       f"not {type(bad).__name__}"):
        run(bad)
    path = tmp_path / "tiny.toml"
    path.write_text((ROOT / "scenes" / "void1d.toml").read_text().replace("ensemble = 20000", "ensemble = 2"))
    res = run(str(path))
    assert res.scene == load_scene(path) and res.scene.name == "tiny" and res.scene.method.ensemble == 2


def test_every_way_to_a_scene_is_validated_before_it_runs(tmp_path):
    import dataclasses

    scene = load_scene("void1d", cells=[8], ensemble=2, t_end=0.001)
    with pytest.raises(ti_dk.ConfigError, match=r"ensemble = 0: give a whole number in \[1, 4294967296\]"):
        scene.replace(ensemble=0)
    by_hand = dataclasses.replace(scene, method=dataclasses.replace(scene.method, ensemble=0))
    with pytest.raises(ti_dk.ConfigError, match="ensemble = 0: give a whole number"):
        run(by_hand)
    with pytest.raises(ti_dk.ConfigError, match="checkpoint_every needs an output folder"):  # it was dropped
        run(scene, checkpoint_every=5)
    for member0 in (-1, 2**32 - 1):  # the last member's index must fit 32 bits
        with pytest.raises(ti_dk.ConfigError, match=rf"member0 = {member0}: give a whole number in \[0, 4294967294\]"):
            run(scene, member0=member0)
    np.save(tmp_path / "q.npy", np.full(8, 3.0))
    from_file = scene.replace(init="array", density_file=str(tmp_path / "q.npy"))
    np.save(tmp_path / "q.npy", np.full(8, -58.0))  # changed between load and run
    with pytest.raises(ti_dk.ConfigError, match=r"density_file: the initial density is -58 in cell \[0\]"):
        run(from_file)


@pytest.mark.parametrize("length", [8e-59, 8e59])  # cells of volume 1e-59 and 1e59, within the bounds
def test_the_moments_stay_finite_at_the_bounds_of_the_cell_volume(length):
    import warnings

    dt = 0.0625 * (length / 8) ** 2
    scene = load_scene("equilibrium1d", lengths=[length], cells=[8], ensemble=8, t_equil=None, histogram=None, C=0.0625,
                       t_end=20 * dt, output_times=[])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no NumPy overflow
        res = run(scene)
    assert np.all(np.isfinite(res.stats.kurtosis)) and np.all(res.stats.variance > 0)
    assert res.stats.mean[-1] * scene.grid.cell_volume == pytest.approx(5.0, rel=0.5)
