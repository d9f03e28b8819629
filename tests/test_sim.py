"""The run controller: result shapes and units, stationary pooling, the HDF5 record, failures."""
import json

import h5py
import numpy as np
import pytest

import ti_dk
from ti_dk import SimulationError, load_scene, run
from ti_dk import theory


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
        assert json.loads(f.attrs["scene"])["ensemble"] == 50
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
                       output_times=[0.0, 0.001, 0.002])
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
        assert b.attrs["complete"]
    assert [p.name for p in whole.frames] == [p.name for p in resumed.frames]


def test_restart_refuses_other_settings(tmp_path):
    scene = load_scene("void1d", ensemble=4, t_end=0.0005)
    run(scene, out=tmp_path, checkpoint_every=10)
    with pytest.raises(ti_dk.ConfigError, match="other scene settings"):
        run(load_scene("void1d", ensemble=5, t_end=0.0005), restart=tmp_path / "void1d_fv_checkpoint.h5")
