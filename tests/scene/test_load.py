"""Scene loading, flat overrides and the one-line errors for bad input."""
import dataclasses
import warnings

import pytest

from ti_dk import ConfigError, available_scenes, load_scene
from ti_dk.scene.schema import ClampWarning, HybridKeys
from ti_dk.scene.load import parse_value

from ..helpers import ROOT, no_hang


def test_scenes_load_and_override():
    assert {"equilibrium1d", "void1d", "ellipse2d"} <= set(available_scenes())
    s = load_scene("void1d", ppc=5, C=0.05, method="gaussian", ensemble=7, seed=3)
    assert s.init.params["ppc"] == 5 and s.time.C == 0.05 and s.method.name == "gaussian" and s.method.ensemble == 7
    assert s.grid.dim == 1 and s.grid.cells == (100,) and s.grid.boundary == (("periodic", "periodic"),)
    assert s.dt == pytest.approx(0.05 * 1e-4)
    assert s.n_steps == round(0.01 / s.dt)
    assert s.output_steps[-1] == s.n_steps


def test_output_times_past_t_end_are_dropped():
    from ti_dk.scene.load import InputWarning

    with pytest.warns(InputWarning, match=r"output_times 0.005, 0.01 lie past t_end = 0.0025"):  # said (the
        s = load_scene("void1d", t_end=0.0025)  # test run's filter ignores it where it is not the subject)
    assert s.stats.output_times == (0.001, 0.0025)


def test_boundaries_per_axis_and_side():
    s = load_scene("ellipse2d", boundary=[["dirichlet", "neumann"], "periodic"], reservoir_ppc=[[4.0, 0.0], 0.0])
    assert s.grid.boundary == (("dirichlet", "neumann"), ("periodic", "periodic"))
    assert s.grid.reservoir_ppc == ((4.0, 0.0), (0.0, 0.0))


@pytest.mark.parametrize(
    "name, overrides, message",
    [
        ("nope", {}, "unknown scene 'nope'"),
        ("void1d", {"bogus": 1}, "unknown key 'bogus': valid keys are C, "),  # nothing near it
        ("void1d", {"treshold": 1}, "unknown key 'treshold': did you mean threshold? valid keys are C, "),
        ("ellipse2d", {"colour_scale": "log"}, "unknown key 'colour_scale': did you mean color_scale or color_max? "),
        ("void1d", {"void_high": 1}, "did you mean void_hi or void_lo? "),  # the initial condition's own keys too
        ("void1d", {"ensemble": "many"}, "ensemble = 'many': give a whole number"),
        ("void1d", {"ensemble": 0}, "ensemble = 0: give a whole number in [1, 4294967296]"),
        ("void1d", {"cells": [0]}, "give a whole number >= 1"),
        ("void1d", {"cells": [1]}, "every axis needs at least 2 cells"),
        ("void1d", {"cells": [4, 4, 4, 4]}, "give 1, 2 or 3 cell counts"),
        ("void1d", {"lengths": [-1.0]}, "lengths = -1.0"),
        ("void1d", {"C": 1.2}, "beyond the explicit stability limit C < 1"),
        ("ellipse2d", {"C": 0.5}, "beyond the explicit stability limit C < 0.5"),
        ("void1d", {"method": "magic"}, "method = 'magic': use one of fv, gaussian, particle"),
        ("void1d", {"boundary": "sticky"}, "boundary 'sticky' on axis 0"),
        ("void1d", {"boundary": [["periodic", "neumann"]]}, "periodic on one side only"),
        ("void1d", {"t_end": -1.0}, "t_end = -1.0"),
        ("void1d", {"precision": "f16"}, "precision = 'f16'"),
        ("void1d", {"pool_layout": "sparse"}, "pool_layout = 'sparse': use one of flat, pointer"),
        ("void1d", {"regrid_interval": 2**32}, "regrid_interval = 4294967296: give a whole number in [0, 4294967295]"),
        ("void1d", {"sample_every": 2**32}, "sample_every = 4294967296: give a whole number in [1, 4294967295]"),
        ("void1d", {"max_box": 2**31}, "max_box = 2147483648: give a whole number in [1, 2147483647]"),
    ],
)
def test_bad_input_says_what_to_change(name, overrides, message):
    with pytest.raises(ConfigError) as err:
        load_scene(name, **overrides)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_unstable_override_and_clamp_warning():
    assert load_scene("void1d", C=1.2, allow_unstable=True).time.C == 1.2
    with pytest.warns(ClampWarning, match="clamped"):
        load_scene("void1d", C=0.2, method="particle")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scene("void1d", C=0.0625, method="particle")


def test_anisotropic_stability_limit():
    # dx = 1/16, dy = 1/32: dt = C/32², Σ dt/dx_a² = C (1/4 + 1) < 1 needs C < 0.8
    load_scene("ellipse2d", cells=[16, 32], C=0.79, method="fv")  # fv: no particle steps to clamp (no warning)
    with pytest.raises(ConfigError, match="C < 0.8"):
        load_scene("ellipse2d", cells=[16, 32], C=0.81, method="fv")


def test_parse_value():
    assert parse_value("[64, 64]") == [64, 64]
    assert parse_value("0.5") == 0.5 and parse_value("true") is True and parse_value("fv") == "fv"


def test_every_key_declared_once_with_doc_and_defaults_from_regrid():
    from ti_dk.scene.schema import INIT_KEYS, KEYS, SECTIONS, Scene
    from ti_dk.scene.schema import keys_help
    from ti_dk.hybrid.clustering import RegridParams

    fields = [f.metadata.get("flat") or f.name for cls in (*SECTIONS.values(), Scene)
              for f in dataclasses.fields(cls) if "key" in f.metadata]
    assert len(fields) == len(set(fields)) and set(fields) | set(INIT_KEYS) == set(KEYS)
    assert all(k.doc for k in KEYS.values())
    help_text = keys_help()
    assert all(f"  {name} " in help_text for name in KEYS)
    assert help_text in (ROOT / "docs" / "scenes.md").read_text()  # the documented key list
    s, rg = load_scene("ellipse2d", threshold=RegridParams().threshold), RegridParams()
    assert (s.hybrid.buffer, s.hybrid.grid_efficiency, s.hybrid.min_box, s.hybrid.max_box) == (rg.buffer, rg.efficiency, rg.min_box, rg.max_box)
    assert HybridKeys().threshold == rg.threshold


def test_set_values_take_the_keys_kind():
    assert parse_value("2024", "name") == "2024" and parse_value("2024", "seed") == 2024
    assert load_scene("void1d", name=parse_value("2024", "name")).name == "2024"
    assert parse_value("fv", "method") == "fv" and parse_value("[1, 2]", "histogram") == [1, 2]


@pytest.mark.parametrize("seed", [0, 2**31 - 1, 2**31, 2**32, 2**64 - 1])
def test_every_unsigned_64_bit_seed_is_accepted(seed):
    assert load_scene("void1d", seed=seed).method.seed == seed


def test_memory_and_work_estimates():
    from ti_dk.scene.estimates import machine_memory, memory_estimate, work_estimate

    small = load_scene("void1d", ensemble=10)
    est = memory_estimate(small)
    # fv: q and one flux per cell (f64), three host copies: 10 members x 100 cells x (16 + 24) bytes
    assert est["fields"] == 10 * 100 * 16 and est["host copies"] == 10 * 100 * 24
    assert sum(est.values()) < machine_memory()
    assert work_estimate(small)[0] == small.n_steps
    # the hybrid's particles and regrids are part of its time: sphere3d ran 6.6 min (RESULTS.md)
    fv, hy = (work_estimate(load_scene("sphere3d", method=m, compare="none"))[1] for m in ("fv", "hybrid"))
    assert hy > 2 * fv and 200 < work_estimate(load_scene("sphere3d"))[1] < 800
    big = dict(cells=[40000, 40000], method="fv")
    with pytest.raises(ConfigError, match=r"needs about \d.* GiB .* but this machine has"):
        load_scene("ellipse2d", **big)


def test_python_callers_may_pass_tuples_and_numpy_numbers():
    import numpy as np

    s = load_scene("ellipse2d", cells=(16, np.int64(16)), lengths=(1.0, 2.0), seed=np.uint64(2**64 - 1),
                   boundary=(("neumann", "neumann"), "periodic"), C=np.float32(0.0625))
    assert s.grid.cells == (16, 16) and s.method.seed == 2**64 - 1 and s.grid.boundary[0] == ("neumann", "neumann")


@pytest.mark.parametrize("overrides, message", [  # load_scene's own hostile inputs (the CLI's are in test_scene)
    ({"cells": [16.0, 16]}, "cells = 16.0: give a whole number"),
    ({"ppc_outer": -1}, "ppc_outer = -1.0"),
    ({"seed": 2**64}, "seed = 18446744073709551616"),
    ({"seed": -1}, "seed = -1"),
    ({"name": "a/b"}, "name = 'a/b'"),
    ({"name": 7}, "name = 7"),
    ({"init": "nothing"}, "unknown initial condition 'nothing'"),
    ({"init": 3}, "unknown initial condition 3"),
    ({"t_equil": 1.0}, "t_equil = 1.0"),
    ({"output_times": [0.0, float("nan")]}, "output_times = nan"),
    ({"reservoir_ppc": [[1.0, float("inf")], 0.0]}, "reservoir_ppc = inf"),
    ({"description": 5}, "description = 5"),
])
def test_load_scene_refuses_with_one_line(overrides, message):
    with pytest.raises(ConfigError) as err:
        load_scene("ellipse2d", **overrides)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_sections_mirror_the_tables_and_flat_keys_still_work(tmp_path):
    nested = tmp_path / "nested.toml"
    nested.write_text('[grid]\ncells = [20]\n[init]\nname = "uniform"\nppc = 3\n[time]\nC = 0.05\n'
                      '[method]\nname = "hybrid"\nensemble = 4\n[hybrid]\nthreshold = 2.0\n[output]\nmovie_frames = 5\n')
    s = load_scene(nested, seed=9)
    assert (s.method.name, s.method.ensemble, s.method.seed, s.time.C) == ("hybrid", 4, 9, 0.05)
    assert (s.hybrid.threshold, s.output.movie_frames, s.init.params["ppc"]) == (2.0, 5, 3.0)
    flat = tmp_path / "flat.toml"
    flat.write_text('method = "hybrid"\nensemble = 4\nC = 0.05\nthreshold = 2.0\nmovie_frames = 5\n'
                    '[grid]\ncells = [20]\n[init]\nname = "uniform"\nppc = 3\n')
    assert load_scene(flat, seed=9, name="nested") == s
    assert load_scene(nested, **s.flat()) == s and s.replace(ensemble=2).method.ensemble == 2
    assert s.replace(ppc=4.0, C=0.04) == load_scene(nested, seed=9, ppc=4.0, C=0.04)
    (tmp_path / "wrong.toml").write_text('[grid]\ncells = [20]\nC = 0.1\n[init]\nname = "uniform"\n')
    with pytest.raises(ConfigError, match=r"\[grid\] C: this key belongs in \[time\]"):
        load_scene(tmp_path / "wrong.toml")


def test_a_potential_is_checked_before_anything_runs():
    from ti_dk.scene.load import parse_value

    assert load_scene("trap1d", potential=parse_value("0.5*((x-0.5)/0.08)**2", "potential")).potential.dim == 1
    assert load_scene("trap1d", potential=parse_value("3", "potential"), init="uniform").grid.potential.source == "3"
    for bad, msg in [("y**2", "potential = 'y\\*\\*2': 'y\\*\\*2' uses y but the grid is 1D: use x"),
                     ("__import__('os')", "is not allowed"), ("x +", "not a formula"), (["x"], "give a formula"),
                     ("exp(1e5*x)", "not finite everywhere")]:
        with pytest.raises(ConfigError, match=msg):
            load_scene("trap1d", potential=bad, init="uniform")


@pytest.mark.parametrize("what", ["scene", "npy", "h5", "restart"])
def test_a_fifo_given_as_an_input_file_is_refused_at_once(tmp_path, what):
    """A FIFO with no writer as the scene file, as density_file (.npy, file.h5:/q) or as --restart."""
    import os

    from ti_dk.control.options import check_options

    fifo = tmp_path / {"scene": "s.toml", "npy": "q.npy", "h5": "q.h5", "restart": "c.h5"}[what]
    os.mkfifo(fifo)
    with no_hang(), pytest.raises(ConfigError, match="not a regular file") as err:
        if what == "scene":
            load_scene(fifo)
        elif what == "restart":
            check_options(load_scene("void1d"), restart=fifo)
        else:
            load_scene("void1d", init="array", density_file=f"{fifo}:/q" if what == "h5" else str(fifo))
    assert str(fifo) in str(err.value) and "\n" not in str(err.value)


HUGE = 10**400  # a whole number beyond the largest float
NUMERIC_INIT_SCENES = {"void1d": ("ppc", "void_lo", "void_hi"),
                       "ellipse2d": ("ppc_outer", "ppc_inner", "outer_r", "inner_r"),
                       "sphere3d": ("inner_x", "inner_y", "inner_z")}
LIST_KEYS = {"cells": lambda v: [v], "lengths": lambda v: [v], "reservoir_ppc": lambda v: [[v, 0]],
             "output_times": lambda v: [0.001, v], "histogram": lambda v: [0, v], "t_equil": lambda v: v}


def _numeric_keys():
    from ti_dk.scene.schema import KEYS
    init_keys = {k: scene for scene, ks in NUMERIC_INIT_SCENES.items() for k in ks}
    for name, k in KEYS.items():
        if k.kind in ("real", "int"):
            yield init_keys.get(name, "void1d"), name, (lambda v: v)
    yield from (("void1d", name, wrap) for name, wrap in LIST_KEYS.items())


@pytest.mark.parametrize("scene, name, wrap", list(_numeric_keys()), ids=lambda v: v if isinstance(v, str) else "")
@pytest.mark.parametrize("sign", [1, -1])
def test_a_whole_number_beyond_float_is_refused_in_one_line_for_every_numeric_key(scene, name, wrap, sign, tmp_path):
    """Every numeric key, scalar or list entry, by override, --set and scene file: a ConfigError naming the key."""
    value = wrap(sign * HUGE)
    path = tmp_path / "huge.toml"  # the key at the top of a copy of the scene file, its own line there dropped
    text = (ROOT / "scenes" / f"{scene}.toml").read_text().replace(f"\n{name} =", f"\n# {name} =")
    path.write_text(f"{name} = {value}\n{text}")
    for load in (lambda: load_scene(scene, **{name: value}),
                 lambda: load_scene(scene, **{name: parse_value(str(value), name)}),
                 lambda: load_scene(path)):
        with pytest.raises(ConfigError) as err:
            load()
        assert name in str(err.value) and "\n" not in str(err.value) and len(str(err.value)) < 300


@pytest.mark.parametrize("length", [1e-100, 1e100, 1e-61, 9e60])
def test_lengths_whose_cells_break_the_fourth_moments_are_refused(length):
    """lengths = [1e-100] or [1e100] gave a NaN kurtosis with a NumPy overflow warning."""
    with pytest.raises(ConfigError, match=r"lengths = .*: a cell's volume .* lies outside \[1e-60, 1e\+60\], where the "
                       "fourth moments of the density"):
        load_scene("void1d", lengths=[length], cells=[8], t_end=1e-3 * length**2)
