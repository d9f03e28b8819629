"""The pilot's files: the picked scene written as TOML loads back as the same scene; the table's layout."""
import ti_dk
from ti_dk.core.bias import MOMENTS, SUMMARIES
from ti_dk.output import tradeoff as out


def test_every_scene_round_trips_through_its_toml(tmp_path):
    for name in ti_dk.available_scenes():
        scene = ti_dk.load_scene(name, ensemble=7, seed=3)
        path = tmp_path / f"{name}.toml"
        path.write_text(out.scene_toml(scene, "a comment\non two lines"))
        assert ti_dk.load_scene(path).to_dict() == scene.to_dict(), name


def test_table_and_columns():
    summaries = {(k, s): (0.5, 0.25, 0.75) for k in MOMENTS for s in SUMMARIES}
    row = {"label": "fv", "overrides": {"method": "fv"}, "cost": 12.0, "wall": 3.0, "error": (0.5, 0.25, 0.75),
           "pareto": True, "meets": None, "sure": True, "negative_cells": 2, "same_as": ["a", "b"],
           "summaries": summaries}
    text = out.table([row], "rel").splitlines()
    assert text[0].split() == ["setting", "cost", "[s]", "mean", "var", "skew", "kurt", "error", "front", "meets"]
    assert text[1].split()[:4] == ["fv", "12", "50%", "[25%–75%]"] and text[1].rstrip().endswith("★")
    cols = out.columns(row)
    assert cols["variance_z_high"] == 0.75 and cols["indistinguishable_from"] == "a; b"
    assert cols["overrides"] == '{"method": "fv"}'
