"""Particles against exact answers: Binomial counts at equilibrium, Poisson-binomial counts for the
void, exact particle balance with Dirichlet reservoirs."""
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
