"""The speed/accuracy pilot on a tiny scene: a second particle ensemble scores no bias within its
stated uncertainty, the files and the picked scene file; the front and the pick on rows made up."""
import csv

import h5py
import numpy as np
import pytest

import ti_dk
from ti_dk.control import tradeoff as tr

TINY = dict(cells=[16], t_end=0.004, output_times=[0.002, 0.004], ppc=12)  # void1d on 16 cells: 16 steps


def test_pilot_on_a_tiny_scene(tmp_path):
    scene = ti_dk.load_scene("void1d", **TINY)
    tries = [tr.Candidate.parse("method=particle seed=7"), tr.Candidate.parse("method=fv")]
    res = ti_dk.tradeoff(scene, planned=1000, accuracy=1e6, tries=tries, defaults=False, pilot_ensemble=60,
                         below=20, out=tmp_path)
    labels = [r["label"] for r in res.rows]
    assert labels == ["particle", "method=particle seed=7", "method=fv"]
    again = res.rows[1]
    assert res.rows[0]["error"] == (0.0, 0.0, 0.0)
    for k in ti_dk.core.bias.MOMENTS:  # no bias: its square is 0 within 2.5 of its SEs
        square, se = again["squares"][k, "z"]
        assert abs(square) < 2.5 * se, (k, square, se)
    assert res.pilot.method.ensemble == 60 and res.times.tolist() == pytest.approx([0.002, 0.004], rel=0.05)
    assert res.cells.shape == (2, 16) and res.cells.any()
    # every setting meets a target of 10⁶ SEs: the cheapest is picked, scaled to the planned ensemble
    assert res.pick == min(res.rows, key=lambda r: r["cost"])["label"]
    picked = ti_dk.load_scene(tmp_path / "void1d_pick.toml")
    assert picked.method.ensemble == 1000 and picked.to_dict() | {"name": 0} == res.pick_scene.to_dict() | {"name": 0}
    assert picked.grid.cells == (16,) and picked.time.t_end == scene.time.t_end
    with open(tmp_path / "tradeoff.csv") as f:
        table = list(csv.DictReader(f))
    assert [t["setting"] for t in table] == labels and float(table[2]["cost_s"]) > 0
    with h5py.File(tmp_path / "tradeoff.h5") as f:
        assert f.attrs["pilot_ensemble"] == 60 and f.attrs["pick"] == res.pick
        assert f["mask"][()].tolist() == res.cells.tolist()
        assert f["cells/method=fv/mean_bias"].shape == (2, 16)
        assert list(f["table/setting"].asstr()[()]) == labels
    assert (tmp_path / "tradeoff.png").stat().st_size > 10_000
    assert "pick:" in res.report() or "use the particle method" in res.report()


def _row(label, cost, square, se):
    return {"label": label, "cost": cost, "overrides": {}, "wall": cost, "negative_cells": 0,
            "scene": ti_dk.load_scene("void1d", method="particle" if label == "particle" else "fv"),
            "squares": {(k, s): (square, se) for k in ti_dk.core.bias.MOMENTS for s in ti_dk.core.bias.SUMMARIES},
            "summaries": {(k, s): ti_dk.core.bias.root(square, se) for k in ti_dk.core.bias.MOMENTS
                          for s in ti_dk.core.bias.SUMMARIES}}


def _judge(rows, target):
    scene = ti_dk.load_scene("void1d")
    return tr._judge(rows, 100, scene, "z", target, scene, np.ones((1, 4), bool), np.array([0.1]), {})


def test_front_and_pick_do_not_tell_apart_what_the_pilot_cannot():
    rows = [_row("particle", 100.0, 0.0, 0.0), _row("a", 1.0, 16.0, 1.0), _row("b", 2.0, 4.0, 1.0),
            _row("c", 3.0, 4.5, 1.0), _row("d", 50.0, 0.5, 0.2)]
    res = _judge(rows, target=2.2)
    front = {r["label"]: r["pareto"] for r in res.rows}
    # c is dearer than b and the pilot cannot tell their errors apart (4.5 − 4 < 2·√2): off the front
    assert front == {"particle": True, "a": True, "b": True, "c": False, "d": True}
    assert res.pick == "b" and res.rows[2]["same_as"] == ["c"]  # b: error 2 ≤ 2.2, the cheapest that meets it
    assert res.pick_scene.method.ensemble == 100 and res.pick_scene.name == "void1d_pick"
    assert "pick: b" in res.answer() and "cannot tell its error from: c" in res.answer()
    assert [r["sure"] for r in res.rows] == [True, True, False, False, True]  # b, c: their bands span 2.2


def test_no_setting_meets_the_target_names_the_particle_method():
    res = _judge([_row("particle", 100.0, 0.0, 0.0), _row("a", 1.0, 16.0, 1.0)], target=1.0)
    assert res.pick == "particle" and res.pick_scene.method.name == "particle"
    assert "no candidate meets error ≤ 1 SE at 100 members: use the particle method" in res.answer()
    res = _judge([_row("particle", 100.0, 0.0, 0.0), _row("a", 1.0, 1.5, 1.0)], target=1.0)
    assert res.pick == "particle" and "they might meet it too" in res.answer()
    assert "a (1.22 [0.707–1.58], 1 s)" in res.answer()


def test_bad_requests_are_refused_with_one_line():
    with pytest.raises(ti_dk.ConfigError, match="not both"):
        ti_dk.tradeoff("void1d", accuracy=1, rel_error=0.1)
    with pytest.raises(ti_dk.ConfigError, match="above 0"):
        ti_dk.tradeoff("void1d", accuracy=0)
    with pytest.raises(ti_dk.ConfigError, match="after t_equil"):
        ti_dk.tradeoff("trap1d", pilot_t_end=0.005)
    with pytest.raises(ti_dk.ConfigError, match="KEY=VALUE"):
        tr.Candidate.parse("threshold")


def test_default_candidates_span_the_settings():
    labels = [c.label for c in tr.candidates(ti_dk.load_scene("ellipse2d"))]
    assert labels[:2] == ["fv", "gaussian"] and "hybrid threshold 6" in labels and "hybrid threshold 12" in labels
    assert any("substeps" in x for x in labels) and any("f32" in x for x in labels) and "fv C=0.125" in labels
    assert "hybrid region_from mean" in labels  # ellipse2d regrids, each member's own region
    assert not any("region_from" in c.label for c in tr.candidates(ti_dk.load_scene("void1d")))  # a fixed region


def test_run_keeps_the_samples_behind_each_row():
    """``run(samples=True)``: each row's moments are those of its samples (a stationary row pools its steps)."""
    for name, keys, per_member in (("void1d", TINY, 1), ("trap1d", dict(cells=[8], t_end=0.08, t_equil=0.04,
                                                                          sample_every=16), 3)):
        res = ti_dk.run(ti_dk.load_scene(name, method="fv", ensemble=5, **keys), samples=True)
        assert len(res.samples) == len(res.times) and res.samples[-1].shape == (per_member, 5, *res.scene.grid.cells)
        for i, x in enumerate(res.samples):
            value, _ = ti_dk.core.bias.moments(x)
            np.testing.assert_allclose(value["mean"], res.stats.mean[i], rtol=1e-12)
            np.testing.assert_allclose(value["variance"], res.stats.variance[i], rtol=1e-9)
    assert ti_dk.run(ti_dk.load_scene("void1d", method="fv", ensemble=2, **TINY)).samples is None
