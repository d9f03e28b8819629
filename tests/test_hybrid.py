"""The AMAR hybrid against exact answers: conservation to round-off, the regrid ledger, the
Poisson-binomial void, positivity, one ghost set per cell and independence of the box layout."""
import numpy as np
import pytest

from ti_dk import load_scene, run, theory
from ti_dk.regrid import mask
from ti_dk.sim import make_solver

from .helpers import as_counts, check_moments


def _solver(scene):
    return make_solver(scene, scene.initial_ppc)


def _run_steps(s, steps, check=None):
    """Step ``s``; return every diagnostic per step, index 0 being the state after the start."""
    rows = [s.diagnostics()]
    for n in range(steps):
        s.step(n)
        rows.append(s.diagnostics())
        if check:
            check(s)
    return {k: np.array([r[k] for r in rows]) for k in rows[0]}


def _covered_nonnegative(s):
    q, region = s.density(), s.region()
    assert np.all(q[region] >= 0)
    # covered cells hold whole particles, and they are the particles in the pool
    counts = q[region] * s.grid.cell_volume
    assert np.allclose(counts, np.round(counts), atol=1e-9)
    assert round(counts.sum()) == s.diagnostics()["particles"]


@pytest.mark.parametrize("cells,boundary", [([100], "periodic"), ([24, 20], "neumann"), ([10, 12, 8], "periodic"),
                                            ([8, 8, 10], "neumann")])
def test_fixed_region_conserves_mass(cells, boundary):
    # the void is tagged at the start and kept: particles cross the region's edge in both directions
    scene = load_scene("void1d", method="hybrid", regrid_interval=0, ensemble=3, cells=cells, boundary=boundary,
                       ppc=8, seed=3)
    s = _solver(scene)
    assert 0 < s.region().mean() < 1
    mass = _run_steps(s, 40, _covered_nonnegative)["mass"]
    assert np.abs(mass / mass[0] - 1).max() < 1e-12
    assert s.diagnostics()["particles"] > 0


def test_regrid_ledger_and_region_follows_density():
    # 2D ellipses: the empty ring is tagged; as it fills cells leave the region and, as the inner
    # ellipse empties, new cells enter it
    scene = load_scene("ellipse2d", method="hybrid", cells=[40, 40], regrid_interval=4, ppc_outer=12,
                       ppc_inner=6, threshold=4.0, t_end=0.01, seed=5)
    s = _solver(scene)
    start = s.region()
    ever, left = start.copy(), np.zeros_like(start)

    def track(s):
        _covered_nonnegative(s)
        r = s.region()
        left[...] |= start & ~r
        ever[...] |= r

    h = _run_steps(s, 120, track)
    mass, change = h["mass"], h["regrid_change"]
    # exact ledger: the only change of the total is what regrids created minus what they removed
    assert np.allclose(np.diff(mass), change[1:], rtol=0, atol=1e-9 * mass[0])
    assert any(change[1:])
    assert left.sum() > 20 and (ever & ~start).sum() > 20
    log = s.regrids
    assert [r["step"] for r in log] == list(range(0, 120, 4))
    assert sum(r["created"] - r["removed"] for r in log[1:]) == pytest.approx(change.sum(), abs=1e-9)


def test_dirichlet_ledger():
    # a region on the low reservoir wall, SPDE on the high one: Δ total = SPDE boundary flux of
    # uncovered cells + particles injected − absorbed at covered ones
    scene = load_scene("void1d", method="hybrid", regrid_interval=0, cells=[30], ensemble=4,
                       boundary=[["dirichlet", "dirichlet"]], reservoir_ppc=[[3.0, 12.0]], void_lo=-1,
                       void_hi=0.2, ppc=10)
    s = _solver(scene)
    region = s.region()[0]
    assert region[0] and not region[-1]
    h = _run_steps(s, 200, _covered_nonnegative)
    mass, inflow = h["mass"], h["boundary_inflow"][1:]
    assert np.allclose(np.diff(mass), inflow, rtol=0, atol=1e-9 * mass[0])
    assert inflow.sum() != 0


def test_box_layout_does_not_matter_and_shared_ghosts_are_sampled_once():
    scene = load_scene("equilibrium1d", method="hybrid", cells=[16, 16], regrid_interval=0, threshold=1, ppc=3,
                       t_equil=None, histogram=None, seed=7, ensemble=1)
    one = [((2, 2), (7, 12)), ((8, 2), (12, 12))]  # two boxes with a one-cell gap (x = 7) between them
    other = [((2, 2), (5, 7)), ((2, 7), (7, 12)), ((5, 2), (7, 7)), ((8, 2), (12, 5)), ((8, 5), (12, 12))]
    assert np.array_equal(mask(one, (16, 16)), mask(other, (16, 16)))
    final = []
    for boxes in (one, other):
        s = _solver(scene)
        s.set_region(mask(boxes, (16, 16))[None], 0)
        # 3 particles per cell everywhere: the ghost ring gets exactly 3 per ghost cell, once each,
        # the gap column included although it borders both boxes
        s._fill(s.pool, s.cur, 0, s.n_ring)
        n_ghost = s.pool.n.to_numpy()[s.cur, 0] - s.n_real.to_numpy()[0]
        assert n_ghost == 3 * s.ring.to_numpy().sum() == 3 * (12 * 12 - 9 * 10)
        _run_steps(s, 30)
        final.append(s.density())
    assert np.array_equal(final[0], final[1])


@pytest.mark.slow  # statistical: thousands of members against the exact counts
def test_void_hybrid_is_poisson_binomial_where_spdes_are_not():
    members = 2000
    common = dict(ensemble=members, t_end=0.0025, output_times=[0.0025])
    hyb = run(load_scene("void1d", method="hybrid", regrid_interval=0, **common))
    gau = run(load_scene("void1d", method="gaussian", **common))
    t = hyb.times[-1]
    ppc0 = np.where(np.abs((np.arange(100) + 0.5) / 100 - 0.5) <= 0.25, 0, 20)
    mean = theory.particle_counts_periodic1d(ppc0, 1.0, t)["mean"]
    cells = (mean > 0.5) & (mean < 5)  # low density, inside the particle region
    assert cells.sum() >= 10
    exact, se = theory.void_reference(ppc0, 1.0, t, members, cells)
    check_moments(as_counts(hyb.stats, -1, hyb.cell_volume), exact, se, cells)
    # the Gaussian SPDE has no skewness: far off the exact value in these cells
    z = (as_counts(gau.stats, -1, gau.cell_volume)["skewness"] - exact["skewness"]) / se["skewness"]
    assert np.median(np.abs(z[cells])) > 10
