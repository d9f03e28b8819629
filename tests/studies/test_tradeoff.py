"""The trade's error measures are calibrated on the exact method and its Pareto front is exact."""
import json

import h5py
import numpy as np
import pytest

from studies import tradeoff
from ti_dk import load_scene, run

from ..helpers import command


def test_pareto_front():
    cost = np.array([1.0, 2.0, 3.0, 1.5, 4.0])
    err = np.array([5.0, 2.0, 1.0, 6.0, 1.0])
    assert tradeoff.pareto(cost, err).tolist() == [True, True, True, False, False]


@pytest.mark.slow  # statistical: 600-member void1d runs (~10 s)
def test_errors_are_one_for_the_exact_method_and_not_for_the_gaussian():
    common = dict(ensemble=600, t_end=0.0025, output_times=[0.0025])
    part = run(load_scene("void1d", method="particle", **common))
    gau = run(load_scene("void1d", method="gaussian", **common))
    e_part = tradeoff.void_error(part)
    e_gau = tradeoff.void_error(gau)
    assert all(0.5 < e_part[k] < 1.6 for k in tradeoff.KEYS), e_part
    assert e_gau["skewness"] > 4, e_gau
    ell = run(load_scene("ellipse2d", method="particle", cells=[32, 32], compare="none", t_end=0.00096))
    assert 0.85 < tradeoff.ellipse_error(ell)["chi2"] < 1.15


def test_criterion_picks_the_smallest_threshold_within_tolerance():
    rows = [{"setting": f"hybrid threshold {t}", "error": e} for t, e in ((1, 3.0), (2, 1.9), (5, 1.2), (10, 2.5))]
    assert tradeoff.criterion(rows + [{"setting": "fv", "error": 0.5}], tolerance=2.0) == 2.0
    assert tradeoff.criterion(rows) == 5.0


def test_tradeoff_command_on_two_settings(tmp_path):
    r = command("studies.tradeoff", "--only", "fv", "particle", "--ensemble", "4", "--t-end", "0.0005", "--cells", "8",
              "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "tradeoff.h5") as f:
        rows = {k: json.loads(f.attrs[k]) for k in ("void1d", "ellipse2d")}
    for name, rs in rows.items():
        assert [x["setting"] for x in rs] == ["particle", "fv"] if name == "void1d" else ["fv", "particle"]
        assert all(x["wall_time"] > 0 for x in rs)
        for x in rs:  # each score is the one its run file gives
            assert (tmp_path / "runs" / name / x["setting"] / f"{name}_{x['setting']}.h5").exists()
    assert rows["void1d"][0]["negative_cells"] == 0 < rows["void1d"][1]["negative_cells"]  # fv goes negative
    md = (tmp_path / "tradeoff.md").read_text()
    assert "## ellipse2d (8², t = 0.00096)" in md  # the scene's output time
    assert (tmp_path / "tradeoff.png").stat().st_size > 10_000
    bad = command("studies.tradeoff", "--only", "nonsense", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "no such setting" in bad.stderr and not (tmp_path / "bad").exists()
