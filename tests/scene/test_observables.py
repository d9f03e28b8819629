"""``[observables]``: conditions read by the safe formula code, the cells whose centre satisfies
them, one-line refusals, and what a run records for them."""
import numpy as np
import pytest

import ti_dk
from ti_dk import ConfigError, load_scene
from ti_dk.scene.observables import mask, read


def test_a_region_is_the_cells_whose_centre_satisfies_its_condition():
    x = (np.arange(10) + 0.5) / 10
    assert np.array_equal(mask("x < 0.5", (10,), (1.0,)), x < 0.5)
    assert np.array_equal(mask("0.2 < x <= 0.45 or x >= 0.9", (10,), (1.0,)), ((x > 0.2) & (x <= 0.45)) | (x >= 0.9))
    assert np.array_equal(mask("not x < 3", (10,), (4.0,)), 4 * x >= 3)  # lengths in L
    xx, yy = np.meshgrid(x, (np.arange(4) + 0.5) / 4, indexing="ij")
    got = mask("(x-0.5)**2 + (y-0.5)**2 < 0.3**2 and step(y - 0.5) > 0", (10, 4), (1.0, 1.0))
    assert np.array_equal(got, ((xx - 0.5) ** 2 + (yy - 0.5) ** 2 < 0.09) & (yy >= 0.5))
    assert np.array_equal(mask("y", (3, 2), (1.0, 1.0)), np.ones((3, 2), bool))  # nonzero: true
    assert not mask("(x-x)/(x-x) > -1 or (x-x)/(x-x)", (4,), (1.0,)).any()  # NaN: false


@pytest.mark.parametrize("table, message", [
    ({"time": "x < 1"}, "'time' is taken by the run's own series"),
    ({"two words": "x < 1"}, "'two words' is not a plain name"),
    ({"a": "x < 0"}, "a = 'x < 0': holds no cell centre of the grid: widen it"),
    ({"a": "z < 0.5"}, "uses z but the grid is 2D: use x, y"),
    ({"a": "__import__('os')"}, "is not allowed"),
    ({"a": "x == 0.5"}, "is not allowed"),
    ({"a": 3}, "give a condition in x, y, z as text"),
    ("x < 0.5", "give a table \\[observables\\] of name = "),
])
def test_bad_observables_are_refused_in_one_line(table, message):
    with pytest.raises(ConfigError, match=message):
        load_scene("ellipse2d", observables=table)


def test_a_scene_file_table_is_read_and_kept_in_the_scene(tmp_path):
    path = tmp_path / "own.toml"
    path.write_text('[grid]\ncells = [8]\n[init]\nname = "uniform"\nppc = 3\n'
                    '[observables]\nleft = "x < 0.5"\nedge = "x < 0.2 or x > 0.8"\n')
    scene = load_scene(path)
    assert scene.stats.observables == (("left", "x < 0.5"), ("edge", "x < 0.2 or x > 0.8"))
    assert scene.observe_every == scene.stats.sample_every == 1
    assert read(scene.stats.observables, (8,), (1.0,)) == scene.stats.observables  # pairs read back alike
    assert load_scene(path, observables={}).stats.observables == ()


@pytest.mark.parametrize("method", ["fv", "gaussian", "particle", "hybrid"])
def test_every_method_records_its_regions_particles_per_member(method):
    # void1d: 20 particles per cell outside the void [0.25, 0.75), periodic; 4 members
    scene = load_scene("void1d", method=method, ensemble=4, t_end=0.002, sample_every=7, output_times=[],
                       observables={"left": "x < 0.5", "right": "x >= 0.5", "void": "0.25 < x < 0.75"})
    res = ti_dk.run(scene, progress=False)
    s, n = res.series, scene.n_steps
    assert s["time"].tolist() == pytest.approx([k * scene.dt for k in (*range(0, n, 7), n)])
    assert s["left"].shape == (len(s["time"]), 4)
    x = (np.arange(100) + 0.5) / 100
    start = scene.initial_ppc
    for name, inside in (("left", x < 0.5), ("right", x >= 0.5), ("void", (x > 0.25) & (x < 0.75))):
        assert s[name][0] == pytest.approx(np.full(4, start[inside].sum()), rel=1e-12)  # the start, exactly
    assert s["left"] + s["right"] == pytest.approx(s["mass"], rel=1e-12)  # the halves hold every particle
    assert s["mass"] == pytest.approx(np.full_like(s["mass"], 1000.0), rel=1e-12)  # periodic: conserved
    assert s["void"][-1].mean() > 0  # particles have entered the void
    final = res.final_density * scene.grid.cell_volume
    assert s["void"][-1] == pytest.approx(final[:, (x > 0.25) & (x < 0.75)].sum(axis=1), rel=1e-12)
    if method == "hybrid":
        assert {"particles", "region_cells"} <= set(s) and s["region_cells"][0].min() > 0
