"""The study is a user of ti_dk.tradeoff: its criterion, and its command on two settings."""
import json

import h5py

from studies import tradeoff

from ..helpers import command


def test_criterion_picks_the_smallest_threshold_within_tolerance():
    rows = [{"label": f"hybrid threshold {t}", "error": (e, e, e)} for t, e in ((1, 3.0), (2, 1.9), (5, 1.2), (10, 2.5))]
    assert tradeoff.criterion(rows + [{"label": "fv", "error": (0.5, 0.5, 0.5)}], tolerance=2.0) == 2.0
    assert tradeoff.criterion(rows) == 5.0


def test_tradeoff_command_on_two_settings(tmp_path):
    r = command("studies.tradeoff", "--only", "fv", "particle", "--ensemble", "8", "--t-end", "0.0005", "--cells", "16",
                "--ellipse-members", "4", "--planned", "100", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "tradeoff.h5") as f:
        rows = {k: json.loads(f.attrs[k]) for k in ("void1d", "ellipse2d")}
    for name, rs in rows.items():
        assert [x["label"] for x in rs] == ["particle", "fv"]  # the reference first
        assert all(x["cost"] > 0 for x in rs) and rs[0]["error"] == [0, 0, 0]
        assert (tmp_path / name / "tradeoff.csv").exists() and (tmp_path / name / "tradeoff.png").exists()
    assert rows["void1d"][0]["negative_cells"] == 0 < rows["void1d"][1]["negative_cells"]  # fv goes negative
    md = (tmp_path / "tradeoff.md").read_text()
    assert "## ellipse2d (16², t = 0.00096, pilot 4 members)" in md  # the scene's output time
    assert "errors in SEs of 100 members" in md
    assert (tmp_path / "tradeoff.png").stat().st_size > 10_000
    bad = command("studies.tradeoff", "--only", "nonsense", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "no such setting" in bad.stderr and not (tmp_path / "bad").exists()
