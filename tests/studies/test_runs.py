"""A study's runs: written once by ti_dk.run, read back whole, run again only when the scene differs."""
import h5py
import numpy as np
import pytest

import ti_dk
from studies import runs as study_runs
from studies.runs import Runs, parse_sets, read_run


def test_read_back_equals_the_result_and_is_reused(tmp_path, monkeypatch):
    runs = Runs(tmp_path)
    keys = dict(method="gaussian", ppc=3, cells=[12], ensemble=6, t_end=0.01, t_equil=0.005, sample_every=4)
    calls = []
    real_run = ti_dk.run
    monkeypatch.setattr(ti_dk, "run", lambda *a, **k: calls.append(1) or real_run(*a, **k))
    got = runs.get("a", "equilibrium1d", **keys)
    want = real_run(runs.scene("equilibrium1d", **keys))  # the same scene in process, no file
    assert got.path == tmp_path / "a" / "equilibrium1d_gaussian.h5" and len(calls) == 1
    assert np.array_equal(got.times, want.times) and got.stats.hist_lo == want.stats.hist_lo == -10
    for k in ("mean", "variance", "skewness", "kurtosis", "n_samples", "histogram"):
        assert np.array_equal(getattr(got.stats, k), getattr(want.stats, k), equal_nan=True), k
    assert np.array_equal(got.diagnostics["mass"], want.diagnostics["mass"])
    assert got.wall_time > 0 and got.cell_volume == pytest.approx(1 / 12)
    again = runs.get("a", "equilibrium1d", **keys)  # the file records this very scene: read, not run
    assert len(calls) == 1 and np.array_equal(again.stats.mean, got.stats.mean)
    runs.get("a", "equilibrium1d", **keys | {"seed": 9})  # another scene: run again
    assert len(calls) == 2
    with h5py.File(got.path, "a") as f:  # a run that never finished is run again
        f.attrs["complete"] = False
    Runs(tmp_path).get("a", "equilibrium1d", **keys | {"seed": 9})
    assert len(calls) == 3
    Runs(tmp_path, rerun=True).get("a", "equilibrium1d", **keys | {"seed": 9})
    assert len(calls) == 4


def test_overrides_win_and_one_member_files_hold_only_the_mean(tmp_path):
    runs = Runs(tmp_path, overrides=parse_sets(["cells=[10]", "t_end=0.002"]))
    got = runs.get("b", "void1d", method="fv", ensemble=1, cells=[50])
    assert got.scene.grid.cells == (10,) and got.stats.mean.shape[1:] == (10,)
    assert np.isnan(got.stats.variance).all()  # undefined for one member, and read as such
    assert np.array_equal(got.stats.mean[-1], read_run(got.path, got.scene).stats.mean[-1])
    with pytest.raises(ti_dk.ConfigError, match="write KEY=VALUE"):
        parse_sets(["cells"])
    assert not study_runs.recorded(tmp_path / "nothing.h5", got.scene)
