"""The drift of an external potential: the deterministic scheme keeps e^{-Ū} stationary to
round-off (Neumann, periodic and Dirichlet sides), its time-step limit, and the equilibrium of the
harmonic trap in every method against the exact cell-averaged Boltzmann profile."""
import math

import numpy as np
import pytest

from ti_dk import ConfigError, load_scene, run
from ti_dk.control.registry import make_solver
from ti_dk.core import theory
from ti_dk.core.grid import Grid
from ti_dk.methods.fluxes import bernoulli, drift_coefficients, stability_number

from ..helpers import KEYS, as_counts, check_moments, fv_mean_step

SIGMA = 0.08  # the trap of scenes/trap1d.toml: U = ½((x − ½)/σ)²


def _trap_mass(n: int) -> np.ndarray:
    """Each cell's share of the Gaussian N(½, σ²) on [0, 1] (erfc from the near tail: no cancellation)."""
    z = (np.linspace(0, 1, n + 1) - 0.5) / (SIGMA * math.sqrt(2))
    mass = np.array([0.5 * (math.erfc(a) - math.erfc(b)) if a >= 0 else 0.5 * (math.erfc(-b) - math.erfc(-a))
                     for a, b in zip(z[:-1], z[1:])])
    return mass / mass.sum()


def _mean_after(scene, steps: int, ppc=None) -> tuple[np.ndarray, np.ndarray]:
    """q̄ (the Gaussian scheme's deterministic density) at the start (``ppc``, or the scene's) and
    after ``steps`` steps."""
    solver = make_solver(scene, scene.initial_ppc if ppc is None else ppc)
    q0 = solver.qbar.to_numpy()[0].copy()
    for n in range(steps):
        solver.step(n)
    return q0, solver.qbar.to_numpy()[0]


@pytest.mark.parametrize("overrides", [
    dict(),  # 1D Neumann trap
    dict(cells=[12, 10], boundary=["neumann", "periodic"], potential="((x-0.4)/0.2)**2 + 2*sin(2*pi*y) + x*sin(2*pi*y)"),  # periodic in y
], ids=["trap1d", "2d-neumann-periodic"])
def test_the_deterministic_scheme_keeps_the_boltzmann_profile(overrides):
    scene = load_scene("trap1d", method="gaussian", ensemble=2, **overrides)
    q0, q1 = _mean_after(scene, 400)
    assert np.abs(q1 - q0).max() <= 1e-12 * q0.max()
    # and it is the cell-averaged e^{-U} (quadrature against the exact Gaussian masses in 1D)
    if scene.grid.dim == 1:
        assert np.allclose(q0 * scene.grid.cell_volume, 400 * _trap_mass(40), rtol=1e-12, atol=0)
    # a profile away from it moves: the drift is there at all
    q0, q1 = _mean_after(scene.replace(potential="0.5*((x-0.3)/0.08)**2"), 50, scene.initial_ppc)
    assert np.abs(q1 - q0).max() > 1e-3 * q0.max()


def test_a_reservoir_holds_its_density_at_its_own_potential():
    """Dirichlet sides: reservoir cells at c e^{-Ū} of their own (particles per cell) leave c e^{-Ū}
    stationary, boundary faces included (no flux, no inflow)."""
    scene = load_scene("trap1d", method="gaussian", ensemble=1, potential="3*x + 0.5*sin(4*x)",
                       boundary="dirichlet", init="boltzmann", ppc=10)
    ubar = scene.potential.cell_values((40,), (1.0,), pad=1)
    c = scene.initial_ppc[0] / math.exp(-ubar[1])
    scene = scene.replace(reservoir_ppc=((c * math.exp(-ubar[0]), c * math.exp(-ubar[-1])),))
    solver = make_solver(scene, scene.initial_ppc)
    q0 = solver.qbar.to_numpy()[0].copy()
    for n in range(300):
        solver.step(n)
    assert np.abs(solver.qbar.to_numpy()[0] - q0).max() <= 1e-12 * q0.max()


def test_scharfetter_gummel_weights():
    z = np.array([-800.0, -30.0, -1e-9, 0.0, 1e-9, 0.7, 30.0, 800.0])
    b = bernoulli(z)
    assert np.allclose(b, [800.0, 30 / (1 - math.exp(-30)), 1, 1, 1, 0.7 / math.expm1(0.7), 30 / math.expm1(30), 0],
                       rtol=1e-9, atol=1e-300)
    assert np.allclose(bernoulli(-z), b + z, rtol=1e-12)  # B(−z) = B(z) + z: the weights differ by δ
    scene = load_scene("trap1d", cells=[16], boundary="periodic", potential="sin(2*pi*x)")
    coef = drift_coefficients(Grid.from_scene(scene))
    ubar = scene.potential.cell_values((16,), (1.0,))
    delta = ubar - np.roll(ubar, 1)  # face i: right cell i, left cell i − 1 (periodic)
    assert np.allclose(coef[:16, 1] - coef[:16, 0], delta, rtol=0, atol=1e-14)
    assert np.array_equal(coef[16], coef[0])  # the upper boundary face is face 0


def test_the_drift_enters_the_time_step_limit():
    scene = load_scene("trap1d")
    grid, flat = Grid.from_scene(scene), Grid.from_scene(scene.replace(potential="", init="uniform"))
    assert stability_number(grid, scene.dt) > stability_number(flat, scene.dt)  # the steep walls of the trap
    # without a potential the weights are 1 and the number is the diffusive Σ Δt/Δx²
    assert flat.potential is None
    steep = "40*(x-0.5)**2/0.08"
    limit = scene.time.C / stability_number(Grid.from_scene(scene.replace(potential=steep, allow_unstable=True)),
                                            scene.dt)
    assert limit < scene.time.C / stability_number(flat, scene.dt)  # lower than without the drift
    load_scene("trap1d", potential=steep, C=0.98 * limit)
    with pytest.raises(ConfigError, match="beyond the explicit stability limit .* with this potential"):
        load_scene("trap1d", potential=steep, C=1.02 * limit)
    with pytest.raises(ConfigError, match="not finite everywhere"):
        load_scene("trap1d", potential="log(x - 0.5)", init="uniform")


@pytest.mark.slow  # statistical: 4,000 members against the exact Boltzmann profile
@pytest.mark.parametrize("method", ["particle", "fv", "hybrid"])
def test_the_trap_equilibrium(method):
    """Ensemble means per cell on the cell-averaged Boltzmann profile (N p_i) within 4 standard
    errors; the particles' counts, with the total fixed by the Neumann walls, on the exact
    binomial moments of Bin(N, p_i)."""
    M, t = 4000, 0.02
    scene = load_scene("trap1d", method=method, ensemble=M, t_end=t, t_equil=None, output_times=[t],
                       regrid_interval=0)
    res = run(scene)
    N, p = 400, _trap_mass(40)
    counts = as_counts(res.stats, -1, res.cell_volume)
    se = np.sqrt(np.maximum(counts["variance"], 1e-300) / M)
    cells = N * p > 0.05
    z = (counts["mean"] - N * p)[cells] / se[cells]
    assert np.all(np.abs(z) < 4), z
    if method == "particle":
        cells = N * p > 1
        exact = {k: np.zeros(40) for k in KEYS}
        ses = {k: np.ones(40) for k in KEYS}
        for i in np.flatnonzero(cells):
            b = theory.binomial_moments(N, p[i])
            s = theory.sampling_se(theory.poisson_binomial_pmf(np.array([p[i]]), np.array([N])), M)
            for k in KEYS:
                exact[k][i], ses[k][i] = b[k], s[k]
        check_moments(counts, exact, ses, cells)


@pytest.mark.parametrize("cells, boundary", [
    ((30,), [["dirichlet", "neumann"]]),
    ((9, 8), [["neumann", "dirichlet"], ["periodic", "periodic"]]),
    ((5, 6, 7), [["dirichlet", "dirichlet"], ["neumann", "neumann"], ["periodic", "periodic"]]),
])
def test_the_mean_follows_the_drift_scheme_face_by_face(cells, boundary):
    """q̄ with a potential against the Scharfetter–Gummel scheme written face by face in NumPy, every
    boundary kind on some axis, away from equilibrium."""
    # periodic along the periodic axis (y in 2D, z in 3D), as every potential must be
    formula = {1: "3*x", 2: "3*x - 2*cos(2*pi*y)", 3: "3*x - 2*y*y + sin(2*pi*z)"}[len(cells)]
    scene = load_scene("trap1d", method="gaussian", cells=list(cells), boundary=boundary, init="uniform",
                       reservoir_ppc=[[2.0, 3.0]] * len(cells), potential=formula, ensemble=2)
    ppc = np.random.default_rng(2).uniform(0.0, 8.0, size=cells)
    q0, q1 = _mean_after(scene.replace(C=0.1), 6, ppc)
    grid = Grid.from_scene(scene)
    ubar = scene.potential.cell_values(grid.cells, grid.lengths, pad=1)
    q, dt = ppc / grid.cell_volume, 0.1 * min(grid.dx) ** 2
    for _ in range(6):
        q = fv_mean_step(q, grid.dx, dt, [tuple(b) for b in boundary], grid.reservoir, ubar)
    np.testing.assert_allclose(q1, q, rtol=1e-11, atol=0)


@pytest.mark.parametrize("boundary", [[["dirichlet", "neumann"]], "periodic"])
def test_the_fused_1d_step_carries_the_same_drift(boundary):
    """fv's per-member 1D kernel and the hybrid's ``advance``, with a potential:
    the same states to a few ulp (fast-math may fold the constants of each differently)."""
    from ti_dk.core.rng import seed_key
    from ti_dk.methods.fv import SPDESolver

    scene = load_scene("trap1d", cells=[37], boundary=boundary, init="uniform", reservoir_ppc=3.0)
    grid = Grid.from_scene(scene)
    a, b = (SPDESolver(grid, scene.dt, 5, key=seed_key(4)) for _ in range(2))
    ppc = np.random.default_rng(1).uniform(0.0, 40.0, size=37)
    a.initialize(ppc)
    for n in range(20):
        b.q.from_numpy(a.q.to_numpy())
        a.step(n)
        b.advance(n)
        np.testing.assert_allclose(a.q.to_numpy(), b.q.to_numpy(), rtol=1e-12, atol=1e-9)
