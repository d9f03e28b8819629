"""Scene formulas: only the whitelist parses, NumPy and Taichi give the formula's values, derivatives
are exact, and the potential's cell values are the exact cell averages of e^{-U}."""
import math

import numpy as np
import pytest
import taichi as ti

from ti_dk import ConfigError, load_scene
from ti_dk.core.expr import ExprError, Potential, derivative, numpy_value, parse, taichi_value, truth

FORMULAS = {  # text: the same function written in Python
    "0.5*((x-0.5)/0.08)**2": lambda x, y, z: 0.5 * ((x - 0.5) / 0.08) ** 2,
    "((x-0.3)**2*(x-0.7)**2 + (y-0.5)**4)/5e-4": lambda x, y, z: ((x - 0.3) ** 2 * (x - 0.7) ** 2 + (y - 0.5) ** 4) / 5e-4,
    "-sin(2*pi*x)*cos(y) + exp(-z) / sqrt(1 + x*x)": lambda x, y, z: -np.sin(2 * np.pi * x) * np.cos(y)
    + np.exp(-z) / np.sqrt(1 + x * x),
    "log(2 + tanh(x - y)) * abs(z - 0.5) + atan(3*x) - tan(0.5*y) + x**y": lambda x, y, z: np.log(2 + np.tanh(x - y))
    * np.abs(z - 0.5) + np.arctan(3 * x) - np.tan(0.5 * y) + x**y,
    "+x - -y / e": lambda x, y, z: x + y / math.e,
    "x*step(x - 0.5) + step(0.3 - y)*z": lambda x, y, z: x * (x >= 0.5) + (y <= 0.3) * z,
}
POINTS = np.random.default_rng(3).uniform(0.05, 0.95, size=(3, 50))


@pytest.mark.parametrize("text", FORMULAS)
def test_numpy_values_and_derivatives_are_the_formulas(text):
    tree, f = parse(text), FORMULAS[text]
    assert np.allclose(numpy_value(tree, tuple(POINTS)), f(*POINTS), rtol=1e-14, atol=1e-12)
    h = 1e-5
    for a in range(3):
        up, down = POINTS.copy(), POINTS.copy()
        up[a] += h
        down[a] -= h
        fd = (f(*up) - f(*down)) / (2 * h)  # central difference: error ~ h² f''' ≈ 1e-9 here
        assert np.allclose(np.broadcast_to(numpy_value(derivative(tree, a), tuple(POINTS)), fd.shape), fd,
                           rtol=1e-6, atol=1e-5)


def test_derivative_of_the_trap_is_exact():
    d = derivative(parse("0.5*((x-0.5)/0.08)**2"), 0)
    x = np.linspace(0, 1, 11)
    assert np.allclose(numpy_value(d, (x,)), (x - 0.5) / 0.08**2, rtol=1e-14, atol=1e-12)
    assert numpy_value(derivative(parse("3*y + 2"), 0), (x, x)) == 0.0


@pytest.mark.parametrize("text", ["__import__('os').system('true')", "x.real", "[x]", "lambda: 1", "x if y else z",
                                  "q + 1", "sin(x, y)", "min(x, y)", "x < y", "'a'", "True", "exp(x=1)", "",
                                  "1 +", "open('f')"])
def test_only_the_whitelist_parses(text):
    with pytest.raises(ExprError):
        parse(text)


def test_conditions_parse_only_as_conditions_and_are_their_truth_values():
    with pytest.raises(ExprError, match="'x < 0.5' is not allowed"):
        parse("x < 0.5")  # a potential or a density takes no comparison
    x, y = np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 1, 11))
    t = parse("0.2 < x <= 0.4 or not y > 0.5 and step(x - 0.5) * 2", logic=True)
    assert np.array_equal(truth(numpy_value(t, (x, y))), ((0.2 < x) & (x <= 0.4)) | (~(y > 0.5) & (x >= 0.5)))
    with pytest.raises(ExprError, match="< <= > >= and or not"):
        parse("x == 0.5", logic=True)


def test_a_formula_for_another_dimension_says_which_variables_fit():
    with pytest.raises(ExprError, match="uses y but the grid is 1D: use x"):
        Potential.of("x + y", 1)
    assert Potential.of("", 2) is None and Potential.of(None, 2) is None
    assert Potential.of("x*y", 2).tree == parse("x*y")


@ti.kernel
def _eval_kernel(out: ti.template(), pts: ti.types.ndarray(), tree: ti.template()):
    for i in range(out.shape[0]):
        out[i] = taichi_value(tree, [pts[0, i], pts[1, i], pts[2, i]], ti.f64)


@pytest.mark.parametrize("text", FORMULAS)
def test_taichi_values_are_the_formulas(text):
    out = ti.field(ti.f64, shape=POINTS.shape[1])
    tree = parse(text)
    for t in (tree, derivative(tree, 0)):
        _eval_kernel(out, POINTS, t)
        want = np.broadcast_to(numpy_value(t, tuple(POINTS)), out.shape)
        assert np.allclose(out.to_numpy(), want, rtol=1e-13, atol=1e-12)


def test_cell_values_are_the_cell_averages_of_the_boltzmann_factor():
    sigma, n = 0.08, 40
    pot = Potential.of(f"0.5*((x-0.5)/{sigma})**2", 1)
    z = (np.linspace(0, 1, n + 1) - 0.5) / (sigma * math.sqrt(2))
    # Gaussian mass of each cell, from the near tail (no cancellation far out)
    mass = np.array([0.5 * (math.erfc(a) - math.erfc(b)) if a >= 0 else 0.5 * (math.erfc(-b) - math.erfc(-a))
                     for a, b in zip(z[:-1], z[1:])])
    exact = sigma * math.sqrt(2 * math.pi) * mass * n  # (1/Δx) ∫ e^{-U} over each cell
    ubar = pot.cell_values((n,), (1.0,))
    assert np.allclose(np.exp(-ubar), exact, rtol=1e-12, atol=0)
    w = pot.boltzmann_weights((n,), (1.0,))
    assert np.allclose(w, mass / mass.sum(), rtol=1e-12, atol=0)
    padded = pot.cell_values((n,), (1.0,), pad=1)  # one reservoir cell beyond each side
    assert padded.shape == (n + 2,) and np.allclose(padded[1:-1], ubar)
    # a steep potential stays finite: relative to the cell centre, not e^{-U} itself
    assert np.all(np.isfinite(Potential.of("2000*x", 1).cell_values((10,), (1.0,))))


def test_a_callable_potential():
    pot = Potential.of(lambda x, y: (x - 0.5) ** 2 + 0 * y, 2)
    assert pot.tree is None and pot.source.startswith("callable")
    assert pot(np.array([0.5, 1.0]), np.array([0.0])).tolist() == [0.0, 0.25]


@pytest.mark.parametrize("text, what", [
    (" + ".join(["x"] * 1000), "nested 1000 levels deep"), ("*".join(["x"] * 600), "nested 600 levels deep"),
    ("-" * 3000 + "x", "nested"), ("x + " * 25_000 + "x", r"\(100,001 characters\) is too long"),
    ("sin(" * 150 + "x" + ")" * 150, "nested 151 levels deep")])
def test_a_formula_too_long_or_too_deep_is_refused_in_one_line(text, what):
    """Each was a RecursionError: a formula is walked recursively, so its size and depth are bounded."""
    for key in ("potential", "density"):
        overrides = {key: text} if key == "potential" else {"init": "expression", "density": text}
        with pytest.raises(ConfigError, match=f"{what}.*give a formula of at most 5,000 characters and 100 levels"
                           if "levels" in what or "long" in what else what) as err:
            load_scene("trap1d", init="uniform", **overrides) if key == "potential" else load_scene("void1d", **overrides)
        assert "\n" not in str(err.value) and len(str(err.value)) < 300
    assert parse(" + ".join(["x"] * 50))[0] == "add"  # within the bounds: a sum of 50 terms
