"""Initial conditions against exact totals and analytic areas and volumes."""
import math

import numpy as np
import pytest

from ti_dk import ConfigError, load_scene
from ti_dk.core.expr import Potential
from ti_dk.scene import initial
from ti_dk.scene.load import make_scene


def test_uniform_holds_the_stated_number_everywhere():
    q = initial.density_ppc("uniform", {"ppc": 5.0}, (7, 3), (1.0, 2.0))
    assert q.shape == (7, 3) and np.all(q == 5.0) and q.sum() == 5.0 * 21


def test_void_cells_are_empty_and_the_rest_hold_ppc():
    q = load_scene("void1d").initial_ppc  # 100 cells, 20 per cell, void [0.25, 0.75]
    x = (np.arange(100) + 0.5) / 100
    inside = (x >= 0.25) & (x <= 0.75)
    assert inside.sum() == 50 and np.all(q[inside] == 0) and np.all(q[~inside] == 20)
    assert q.sum() == 1000  # the stated total: 20 particles in each of the 50 cells outside
    # coordinates are measured from the lower corner in length units: on [0, 2] with 8 cells
    # the centres 0.375 and 0.625 lie in the void
    assert initial.density_ppc("void", {"ppc": 20.0, "void_lo": 0.25, "void_hi": 0.75}, (8,), (2.0,)).tolist() == \
        [20, 0, 0, 20, 20, 20, 20, 20]
    # in 2D the void is a slab across the second axis
    q2 = initial.density_ppc("void", {"ppc": 3.0, "void_lo": 0.25, "void_hi": 0.75}, (8, 5), (1.0, 1.0))
    assert np.all(q2 == q2[:, :1]) and q2[:, 0].tolist() == [3, 3, 0, 0, 0, 0, 3, 3]


def _ellipse_perimeter(a, b):  # Ramanujan's approximation
    return math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))


def test_ellipses_areas_orientation_and_total():
    ro, ri, n = 0.4, 0.1, 256
    q = initial.density_ppc("ellipses", {"ppc_outer": 30.0, "ppc_inner": 15.0, "outer_r": ro, "inner_r": ri},
                            (n, n), (1.0, 1.0))
    h = 1 / n
    # 0.5(u−v)² + 2(u+v)² = a² + 4b² in the axes a = (u−v)/√2, b = (u+v)/√2: semi-axes r and r/2,
    # area π r²/2; the inner one likewise with the axes swapped. Midpoint-rule error: at most the
    # one layer of cells the boundary crosses, perimeter × h.
    a_outer, a_inner = math.pi * ro**2 / 2, math.pi * ri**2 / 2
    assert abs((q == 0).mean() - (a_outer - a_inner)) < _ellipse_perimeter(ro, ro / 2) * h
    assert abs((q == 15).mean() - a_inner) < _ellipse_perimeter(ri, ri / 2) * h
    assert abs(q.sum() * h * h - (30 * (1 - a_outer) + 15 * a_inner)) < 30 * _ellipse_perimeter(ro, ro / 2) * h
    # the empty ellipse is long along the anti-diagonal, the inner one along the diagonal
    d = 0.3 / math.sqrt(2)
    at = lambda u, v: initial.ellipses((np.array([0.5 + u]), np.array([0.5 + v])))[0]  # noqa: E731
    assert at(d, -d) == 0 and at(d, d) == 30
    d = 0.08 / math.sqrt(2)
    assert at(d, d) == 15 and at(d, -d) == 0


def test_spheres_volumes_and_offset():
    ro, ri, n = 0.4, 0.1, 64
    q = initial.density_ppc("spheres", {"ppc_outer": 30.0, "ppc_inner": 15.0, "outer_r": ro, "inner_r": ri,
                                        "inner_x": 0.1, "inner_y": 0.2, "inner_z": 0.0}, (n, n, n), (1.0, 1.0, 1.0))
    h = 1 / n
    v_outer, v_inner = 4 / 3 * math.pi * ro**3, 4 / 3 * math.pi * ri**3
    assert abs((q == 0).mean() - (v_outer - v_inner)) < 4 * math.pi * (ro**2 + ri**2) * h
    assert abs((q == 15).mean() - v_inner) < 4 * math.pi * ri**2 * h
    # the inner sphere is centred at (0.6, 0.7, 0.5)
    i = round(0.6 / h - 0.5), round(0.7 / h - 0.5), round(0.5 / h - 0.5)
    assert q[i] == 15 and q[n - 1 - i[0], n - 1 - i[1], i[2]] == 0


@pytest.mark.parametrize("name", list(initial.REGISTRY))
def test_every_condition_is_a_nonnegative_float_array_of_the_grid(name, tmp_path):
    cells = {"ellipses": (6, 5), "spheres": (4, 5, 6)}.get(name, (6, 5))
    np.save(tmp_path / "q.npy", np.arange(30.0).reshape(6, 5))
    params = {"expression": {"density": "1 + x*y"}, "array": {"density_file": str(tmp_path / "q.npy")}}.get(name, {})
    q = initial.density_ppc(name, params, cells, (1.0,) * len(cells), Potential.of("(x - 0.5)**2 + y", 2))
    assert q.shape == cells and q.dtype == np.float64 and np.all(q >= 0)


def test_a_density_formula_is_taken_at_the_cell_centres():
    s = make_scene(dict(init="expression", density="3 + 2*sin(2*pi*x)", cells=[8]))
    x = (np.arange(8) + 0.5) / 8
    assert np.allclose(s.initial_ppc, 3 + 2 * np.sin(2 * np.pi * x), rtol=1e-15)
    s = make_scene(dict(init="expression", density="x + 10*y", cells=[4, 2], lengths=[2.0, 1.0], t_end=0.1))
    assert np.allclose(s.initial_ppc, np.add.outer((np.arange(4) + 0.5) / 2, 10 * (np.arange(2) + 0.5) / 2),
                       rtol=1e-15)
    for bad, msg in [("1 - 2*x", r"density: the initial density is -0.125 in cell \[4\]"),
                     ("y", "uses y but the grid is 1D"), ("exp(1000*x)", "give finite densities"),
                     ("import os", "not a formula")]:
        with pytest.raises(ConfigError, match=msg):
            make_scene(dict(init="expression", density=bad, cells=[8]))


def test_a_density_array_from_npy_and_hdf5(tmp_path):
    import h5py

    q = np.random.default_rng(1).uniform(0, 9, size=(6, 4))
    np.save(tmp_path / "q.npy", q)
    with h5py.File(tmp_path / "q.h5", "w") as f:
        f["group/q"] = q
    for path in (tmp_path / "q.npy", f"{tmp_path / 'q.h5'}:/group/q"):
        s = make_scene(dict(init="array", density_file=str(path), cells=[6, 4]))
        assert np.array_equal(s.initial_ppc, q)
    with pytest.raises(ConfigError, match=r"density_file: .* shape \[6, 4\]: give one of shape \[4, 6\]"):
        make_scene(dict(init="array", density_file=str(tmp_path / "q.npy"), cells=[4, 6]))
    for bad in (tmp_path / "none.npy", f"{tmp_path / 'q.h5'}:/nothing"):
        with pytest.raises(ConfigError, match="density_file: cannot read"):
            make_scene(dict(init="array", density_file=str(bad), cells=[6, 4]))


def test_boltzmann_is_the_cell_averaged_equilibrium():
    s = load_scene("trap1d")
    n, sigma = s.grid.cells[0], 0.08
    z = (np.linspace(0, 1, n + 1) - 0.5) / (sigma * math.sqrt(2))
    mass = np.array([0.5 * (math.erfc(a) - math.erfc(b)) if a >= 0 else 0.5 * (math.erfc(-b) - math.erfc(-a))
                     for a, b in zip(z[:-1], z[1:])])
    assert np.allclose(s.initial_ppc, 10 * n * mass / mass.sum(), rtol=1e-12, atol=0)
    with pytest.raises(ConfigError, match="needs a potential"):
        load_scene("trap1d", potential="")


def test_a_shape_for_another_dimension_says_which_fit():
    with pytest.raises(ConfigError, match="'ellipses' is 2D, give 2 cell counts .in 1D use one of uniform, void, "
                                          "expression, array, boltzmann."):
        load_scene("ellipse2d", cells=[16])


@pytest.mark.parametrize("values", [np.array(["2024-01-01"] * 8, dtype="datetime64[D]"), np.full(8, 2 + 1j),
                                    np.full(8, True), np.array(["3"] * 8)], ids=["datetime", "complex", "bool", "text"])
def test_a_density_file_of_anything_but_real_numbers_is_refused(values, tmp_path):
    import h5py

    np.save(tmp_path / "q.npy", values)
    paths = [tmp_path / "q.npy"]
    if values.dtype.kind != "M":  # HDF5 has no datetime type
        with h5py.File(tmp_path / "q.h5", "w") as f:
            f["q"] = values.astype("S") if values.dtype.kind == "U" else values
        paths.append(f"{tmp_path / 'q.h5'}:/q")
    for path in paths:
        with pytest.raises(ConfigError, match=r"density_file: .* holds values of type .*: give real numbers"):
            make_scene(dict(init="array", density_file=str(path), cells=[8]))
    np.save(tmp_path / "q.npy", np.arange(8, dtype=np.uint16))  # whole numbers are real numbers
    assert make_scene(dict(init="array", density_file=str(tmp_path / "q.npy"), cells=[8])).initial_ppc[7] == 7.0


@pytest.mark.parametrize("key", ["outer_r", "inner_r"])
def test_a_radius_beyond_any_box_is_refused_not_an_overflow(key):
    with pytest.raises(ConfigError, match=rf"{key} = 1e\+308: give a number in \[0, 1e\+06\]"):
        load_scene("ellipse2d", **{key: 1e308})
    scene = load_scene("ellipse2d", **{key: 1e6})
    assert scene.initial_ppc.shape == scene.grid.cells
