"""Particles against exact answers: Binomial counts at equilibrium, Poisson-binomial counts for the
void, exact particle balance with Dirichlet reservoirs."""
import math

import numpy as np
import pytest
import taichi as ti

from ti_dk import load_scene, run
from ti_dk.core import theory
from ti_dk.core.grid import Grid
from ti_dk.methods.particles import ParticleSolver
from ti_dk.core.rng import seed_key

from ..helpers import KEYS, as_counts, check_moments, digest_on_threads

@pytest.mark.slow  # statistical: thousands of members against the exact counts
def test_equilibrium_counts_are_binomial():
    scene = load_scene("equilibrium1d", method="particle", particle_init="exact_uniform", ppc=5, ensemble=3000,
                       t_equil=None, t_end=0.002, output_times=[0.0, 0.002], histogram=None)
    res = run(scene)
    N, M = 5 * 100, 100
    b = theory.binomial_moments(N, 1 / M)
    pmf = theory.poisson_binomial_pmf(np.array([1 / M]), np.array([N]))
    se = theory.sampling_se(pmf, scene.method.ensemble)
    exact = {k: np.full(M, b[k]) for k in KEYS}
    ses = {k: np.full(M, se[k]) for k in KEYS}
    for row in range(2):
        check_moments(as_counts(res.stats, row, res.cell_volume), exact, ses, slice(None))
    assert res.diagnostics["mass"][-1] == N * scene.method.ensemble


@pytest.mark.slow  # statistical: thousands of members against the exact counts
def test_void_counts_are_poisson_binomial():
    scene = load_scene("void1d", method="particle", ensemble=1500, t_end=0.0025, output_times=[0.0005, 0.0025])
    res = run(scene)
    ppc0 = np.where(np.abs((np.arange(100) + 0.5) / 100 - 0.5) <= 0.25, 0, 20)
    for row, t in enumerate(res.times):
        steps = round(t / scene.dt)
        P = theory.cell_transition(100, 1.0, scene.dt, steps)
        pmfs = [theory.poisson_binomial_pmf(P[:, i], ppc0) for i in range(100)]
        # low-density cells (the interesting ones) with at least 0.5 particles on average
        cells = np.array([(np.arange(len(p)) * p).sum() for p in pmfs]) > 0.5
        assert cells.sum() > 50
        exact, se = theory.void_reference(ppc0, 1.0, scene.dt, steps, scene.method.ensemble, cells)
        # the PMF route and the cumulant route to the exact moments agree
        assert np.allclose([(np.arange(len(p)) * p).sum() for p in pmfs], exact["mean"])
        assert (exact["mean"][cells] < 5).any()
        check_moments(as_counts(res.stats, row, res.cell_volume), exact, se, cells)


def test_walk_is_reproducible_and_seeded():
    scene = load_scene("void1d", method="particle", ensemble=20, t_end=0.0002)
    a, b = run(scene), run(scene)
    c = run(load_scene("void1d", method="particle", ensemble=20, t_end=0.0002, seed=2))
    assert np.array_equal(a.final_density, b.final_density)
    assert not np.array_equal(a.final_density, c.final_density)


@pytest.mark.parametrize("boundary", ["neumann", [["dirichlet", "dirichlet"]]], ids=["neumann", "dirichlet"])
def test_walls_and_reservoirs(boundary):
    scene = load_scene("equilibrium1d", method="particle", cells=[20], boundary=boundary, reservoir_ppc=6.0,
                       ppc=2, C=0.25, ensemble=200)
    grid = Grid.from_scene(scene)
    ppc = np.full(20, 2.5)
    s = ParticleSolver(grid, scene.dt, scene.method.ensemble, seed_key(4), ti.f64, ParticleSolver.capacity_for(grid, ppc))
    s.initialize(ppc)
    mass = [s.diagnostics()["mass"]]
    inflow, clamped = [], 0
    for n in range(400):
        s.step(n)
        d = s.diagnostics()
        mass.append(d["mass"])
        inflow.append(d["boundary_inflow"])
        clamped += d["clamped_steps"]
    st = s.state()
    x = st["x"][:, :, 0]
    alive = np.arange(x.shape[1])[None, :] < st["n_alive"][:, None]
    assert np.all((x[alive] >= 0) & (x[alive] <= 1))
    assert np.array_equal(np.diff(mass), inflow)  # every particle accounted for, exactly
    assert clamped > 0  # C = 0.25 clamps ~5 % of steps: counted
    if boundary == "neumann":
        assert not any(inflow)
    else:
        # 400 steps of dt = 0.25/400 is t = 0.25: the profile has filled towards the reservoir's 6
        assert 4.5 < mass[-1] / (20 * scene.method.ensemble) < 6.5


_BITS = """
import hashlib, sys
import numpy as np
import ti_dk, taichi as ti
from ti_dk.core.grid import Grid
from ti_dk.methods.particles import ParticleSolver
from ti_dk.core.rng import seed_key
ti_dk.init("cpu", int(sys.argv[1]))
h = hashlib.sha256()
for cells, E, bc in (((50,), 16, ((0, 0),)), ((20, 16), 2, ((2, 1), (0, 0))), ((8, 8, 8), 2, ((0, 0),) * 3)):
    res = tuple((6.0 * c[0], 0.0) for c in [cells] * len(cells)) if bc[0][0] == 2 else ((0.0, 0.0),) * len(cells)
    grid = Grid(cells, (1.0,) * len(cells), bc, res)
    ppc = np.full(cells, 3.5)
    s = ParticleSolver(grid, 0.1 * min(grid.dx) ** 2, E, key=seed_key((1 << 40) + 9), real=ti.f64,
                       capacity=ParticleSolver.capacity_for(grid, ppc))
    s.initialize(ppc)
    for n in range(30):
        s.step(n)
    st = s.state()
    h.update(st["x"].tobytes())
    h.update(st["n_alive"].tobytes())
print(h.hexdigest())
"""


def test_same_seed_same_bits_on_one_and_two_threads():
    """Counter-based walks: the particles after 30 steps are bit-identical whatever the thread count."""
    one, two = digest_on_threads(_BITS)
    assert one == two


def _ou_cell_probabilities(n: int, start: int, t: float, sigma: float = 0.08) -> np.ndarray:
    """Chance that a particle started uniformly in cell ``start`` of [0, 1] lies in each cell at time
    ``t`` under the Ornstein–Uhlenbeck law of U = ½((x − ½)/σ)² (dX = −½U'dt + dW): Gaussian with
    mean ½ + (x₀ − ½)e^{−t/2σ²} and variance σ²(1 − e^{−t/σ²}), averaged over x₀ (Gauss–Legendre)."""
    ndtr = np.vectorize(lambda z: 0.5 * math.erfc(-z / math.sqrt(2)))  # the standard normal CDF
    nodes, weights = np.polynomial.legendre.leggauss(32)
    x0 = (start + 0.5 + 0.5 * nodes) / n
    mean = 0.5 + (x0 - 0.5) * math.exp(-t / (2 * sigma**2))
    sd = sigma * math.sqrt(-math.expm1(-t / sigma**2))
    edges = np.linspace(0, 1, n + 1)
    cdf = ndtr((edges[:, None] - mean[None, :]) / sd)
    return (np.diff(cdf, axis=0) * 0.5 * weights).sum(axis=1)


def test_the_drift_follows_the_ornstein_uhlenbeck_propagator(tmp_path):
    """400 particles per member from one cell of the harmonic trap, short enough (2,000 members,
    t ≈ 0.01: the cloud stays 5 standard deviations from the walls) that the walls do not matter:
    the counts are Bin(400, p_i) with p_i the OU propagator integrated over cell i."""
    n, start, N, M = 40, 11, 400, 2000
    ppc = np.zeros(n)
    ppc[start] = N
    np.save(tmp_path / "start.npy", ppc)
    scene = load_scene("trap1d", method="particle", init="array", density_file=str(tmp_path / "start.npy"),
                       ensemble=M, t_end=0.01, t_equil=None, output_times=[0.01])
    res = run(scene)
    p = _ou_cell_probabilities(n, start, scene.n_steps * scene.dt)
    assert abs(p.sum() - 1) < 1e-7 and res.diagnostics["mass"][-1] == N * M  # < 1e-7 of the Gaussian beyond the walls
    counts = as_counts(res.stats, -1, res.cell_volume)
    cells = N * p > 1
    exact = {k: np.zeros(n) for k in KEYS}
    ses = {k: np.ones(n) for k in KEYS}
    for i in np.flatnonzero(cells):
        b = theory.binomial_moments(N, p[i])
        s = theory.sampling_se(theory.poisson_binomial_pmf(np.array([p[i]]), np.array([N])), M)
        for k in KEYS:
            exact[k][i], ses[k][i] = b[k], s[k]
    z = (counts["mean"] - N * p)[cells] / ses["mean"][cells]
    assert np.all(np.abs(z) < 4), z
    check_moments(counts, exact, ses, cells)


def test_a_callable_potential_is_tabulated_for_the_walk(tmp_path):
    """The same trap as a Python callable (its gradient tabulated for the walk) moves the cloud
    as the formula does: the mean position after t agrees with the OU mean within 4 standard errors."""
    n, start, N, M = 40, 11, 400, 400
    ppc = np.zeros(n)
    ppc[start] = N
    np.save(tmp_path / "start.npy", ppc)
    scene = load_scene("trap1d", method="particle", init="array", density_file=str(tmp_path / "start.npy"),
                       ensemble=M, t_end=0.01, t_equil=None, output_times=[0.01],
                       potential=lambda x: 0.5 * ((x - 0.5) / 0.08) ** 2)
    assert scene.to_dict()["grid"]["potential"] == "callable test_a_callable_potential_is_tabulated_for_the_walk.<locals>.<lambda>"
    res = run(scene)
    p = _ou_cell_probabilities(n, start, scene.n_steps * scene.dt)
    x = (np.arange(n) + 0.5) / n
    mean_x = (res.stats.mean[-1] * res.cell_volume * x).sum() / N
    exact_x = (p * x).sum()
    sd = math.sqrt((p * (x - exact_x) ** 2).sum() / (N * M))
    assert abs(mean_x - exact_x) < 4 * sd
