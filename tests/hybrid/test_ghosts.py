"""Sampling from the SPDE: every particle lies in the cell its identity names, ℓ or ℓ + 1 of them
per cell (reservoir cells included), with the birth word of a ghost or of a regrid."""
import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.scene.schema import ClampWarning
from ti_dk.hybrid.ghosts import REGRID_BIRTH
from ti_dk.core import theory
from ti_dk.control.registry import make_solver


@pytest.mark.parametrize("layout", ["flat", "pointer"])
def test_sampled_particles_lie_in_their_birth_cells(layout):
    scene = load_scene("void1d", method="hybrid", regrid_interval=0, cells=[12, 10], ensemble=2,
                       boundary=[["dirichlet", "neumann"], "periodic"], reservoir_ppc=[[3.5, 0.0], 0.0],
                       void_lo=-1, void_hi=0.3, ppc=6.5, seed=8, pool_layout=layout)
    s = make_solver(scene, scene.initial_ppc)
    step = 4
    s.sampler.fill(s.pool, s.cur, step, s.n_ring, 0.0, 1, 0)
    x, pid, n = s.pool.occupied(s.cur)
    real = s.n_real.to_numpy()
    dx, padded, bits = np.array(scene.grid.dx), s.regions.padded, s.sampler.id_bits
    region, ppc = s.region(), s.density() * scene.grid.cell_volume
    for e in range(2):
        # the particles sampled at the start: in covered cells, flagged as sampled at a regrid
        # (occupied() sorts by identity, so they are told apart from the ghosts by their birth word)
        born = pid[e, :n[e], 1]
        start, ghost = born == REGRID_BIRTH, born == step + 1
        assert start.sum() == real[e] and ghost.sum() == n[e] - real[e]
        cells = np.floor(x[e, :n[e]][start] / dx).astype(int)
        assert region[(e, *cells.T)].all()
        # the ghosts: born at step + 1, each in the cell (or reservoir cell) its id names
        ghosts, ids = x[e, :n[e]][ghost], pid[e, :n[e]][ghost]
        assert ghosts.size
        origin = np.stack(np.unravel_index(ids[:, 0] >> bits, padded), axis=1) - 1
        assert np.array_equal(np.floor(ghosts / dx).astype(int), origin)
        ring = np.argwhere(s.regions.ring_mask[e]) - 1
        assert {tuple(c) for c in origin} <= {tuple(c) for c in ring}
        for c in ring:
            lam = 3.5 if c[0] < 0 else ppc[(e, *c)]
            m = (origin == c).all(axis=1).sum()
            assert np.floor(lam) <= m <= np.ceil(lam)
            k = ids[(origin == c).all(axis=1), 0] & ((1 << bits) - 1)
            assert sorted(k) == list(range(m))  # indices 0 … m − 1 within the cell


@pytest.mark.parametrize("layout,region", [("flat", "slab"), ("pointer", "slab"), ("flat", "boxes")])
def test_walked_fill_keeps_exactly_the_ghosts_that_walk_into_the_region(layout, region):
    """The hybrid's fill walks its ghosts at once (``walked``): it must append exactly the ghosts of
    the plain fill whose step (:meth:`Walker.move`, drawn here separately) ends in a covered cell,
    at that end point, and count the clamped axes of those (the early-out of :meth:`Crossings.walk`
    must drop no ghost that enters)."""
    import taichi as ti

    with pytest.warns(ClampWarning):  # C = 0.5: clamped steps are common, as this test wants
        scene = load_scene("void1d", method="hybrid", regrid_interval=0, cells=[12, 10], ensemble=2,
                           boundary=[["dirichlet", "neumann"], "periodic"], reservoir_ppc=[[3.5, 0.0], 0.0],
                           void_lo=-1, void_hi=0.3, ppc=6.5, seed=8, pool_layout=layout, C=0.5)
    s = make_solver(scene, scene.initial_ppc)
    s.sampler.crossings.direct = False  # every ghost walked (as with a potential); the draw of the crossings: test_crossings
    if region == "boxes":  # 3×3 boxes: ring cells whose only covered neighbour is diagonal (one across y's periodic side)
        mask = np.zeros((2, 12, 10), dtype=np.uint8)
        mask[0, 5:8, 4:7] = mask[1, 5:8, [8, 9, 0]] = 1
        s.regions.load_state({"covered": mask, "boxes": np.zeros((0, 5), dtype=np.int64)})
    step, bits = 4, s.sampler.id_bits
    out = {}
    for walked in (0, 1):
        s.pool.truncate(s.cur)
        s.sampler.fill(s.pool, s.cur, step, s.n_ring, 0.0, 1, walked)
        x, pid, n = s.pool.occupied(s.cur)
        out[walked] = [(x[e, :n[e]][pid[e, :n[e], 1] == step + 1], pid[e, :n[e]][pid[e, :n[e], 1] == step + 1])
                       for e in range(2)]
        if walked:
            clamped = s.sampler.clamped[None]
    walker, covered = s.walker, s.regions.covered
    dx, cells = np.array(scene.grid.dx), np.array(scene.grid.cells)
    total_clamped = 0
    for e in range(2):
        x0, pid0 = out[0][e]
        y = np.zeros_like(x0)
        alive = np.zeros(len(x0), dtype=np.int32)
        ncl = np.zeros(len(x0), dtype=np.int32)

        @ti.kernel
        def move(x: ti.types.ndarray(), pid: ti.types.ndarray(), y: ti.types.ndarray(), alive: ti.types.ndarray(),
                 ncl: ti.types.ndarray(), e: ti.i32):
            for i in range(x.shape[0]):
                z, ok, c = walker.move(ti.Vector([x[i, 0], x[i, 1]]), e, pid[i, 0], pid[i, 1], ti.u32(step))
                y[i, 0], y[i, 1], alive[i], ncl[i] = z[0], z[1], ti.cast(ok, ti.i32), c

        move(x0, pid0, y, alive, ncl, e)
        cell = np.minimum(np.floor(y / dx).astype(int), cells - 1)
        enters = alive.astype(bool) & covered.to_numpy()[(e, *cell.T)].astype(bool)
        x1, pid1 = out[1][e]
        assert 0 < enters.sum() < len(x0)  # some enter, most do not
        total_clamped += ncl[enters].sum()
        expect = sorted(zip(pid0[enters, 0].tolist(), map(tuple, y[enters].tolist())))
        got = sorted(zip(pid1[:, 0].tolist(), map(tuple, x1.tolist())))
        assert got == expect
        assert (pid1[:, 0] >> bits).size == enters.sum()
    assert clamped == total_clamped and total_clamped > 0  # C = 0.5: p = 0.16 per axis


def test_ghosts_lie_as_the_boltzmann_factor_within_their_cell():
    """With a potential the ghosts' in-cell profile is e^{-βu}, β the centred slope of ln q̄: for
    U = g x at equilibrium that is gΔx, so the mean offset in the cell is 1/β − 1/(e^β − 1)
    (0.418 for β = 1, where uniform placement gives 0.5)."""
    scene = load_scene("trap1d", method="hybrid", potential="20*x", cells=[20], ppc=10, ensemble=2000,
                       regrid_interval=0)
    s = make_solver(scene, scene.initial_ppc)
    step = 4
    s.sampler.fill(s.pool, s.cur, step, s.n_ring, 0.0, 1, 0)
    x, pid, n = s.pool.occupied(s.cur)
    u = np.concatenate([x[e, :n[e], 0][pid[e, :n[e], 1] == step + 1] for e in range(2000)]) * 20
    u -= np.floor(u)
    beta = 1.0
    mean = 1 / beta - 1 / np.expm1(beta)
    second = 2 / beta**2 - (1 + 2 / beta) / np.expm1(beta)  # E[u²] of the truncated exponential
    se = np.sqrt((second - mean**2) / u.size)
    assert u.size > 5000 and abs(u.mean() - mean) < 4 * se, (u.mean(), mean, se)


def test_a_steep_curved_trap_keeps_the_walks_stationary_law_in_the_region():
    """Issue 28: in a trap of σ = 0.03 on 40 cells U changes by 1.7 k_BT and curves by
    U''Δx² = 0.7 k_BT across the cells at the region's edge. Ghosts laid on an exponential with
    the centred slope of ln q̄ misjudge the density at the face they enter by about
    (ln q)''Δx²/12, and the covered cells held 6 % more than the walk's stationary law (z ≈ +19
    at this size); laid along e^{−U} within the cell (InCell.place) they hold it. Members are
    independent: each one's time average of the region's count, sampled every 8 steps after the
    first 200 (the start is the cell-averaged Boltzmann state), gives the standard error."""
    sigma, n = 0.03, 40
    scene = load_scene("trap1d", method="hybrid", potential=f"0.5*((x-0.5)/{sigma})**2", cells=[n], C=0.01,
                       ensemble=400, ppc=10, regrid_interval=0, seed=5, t_equil=0.0, t_end=800 * 0.01 / n**2)
    s = make_solver(scene, scene.initial_ppc)
    region = s.region()[0]
    assert region[:18].all() and not region[18:22].any() and region[22:].all()
    total = np.zeros(400)
    samples = 0
    for step in range(800):
        s.step(step)
        if step >= 200 and step % 8 == 0:
            total += (s.density() * s.grid.cell_volume)[:, region].sum(axis=1)
            samples += 1
    total /= samples
    exact = scene.initial_ppc.sum() * theory.trap_walk_shares(n, 1.0, scene.dt, 1 / sigma**2, 0.5)[region].sum()
    z = (total.mean() - exact) / (total.std(ddof=1) / np.sqrt(total.size))
    assert abs(z) < 3.5, (total.mean(), exact, z)
