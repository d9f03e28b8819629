"""Sampling from the SPDE: every particle lies in the cell its identity names, ℓ or ℓ + 1 of them
per cell (reservoir cells included), with the birth word of a ghost or of a regrid."""
import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.ghosts import REGRID_BIRTH
from ti_dk.sim import make_solver


@pytest.mark.parametrize("layout", ["flat", "pointer"])
def test_sampled_particles_lie_in_their_birth_cells(layout):
    scene = load_scene("void1d", method="hybrid", regrid_interval=0, cells=[12, 10], ensemble=2,
                       boundary=[["dirichlet", "neumann"], "periodic"], reservoir_ppc=[[3.5, 0.0], 0.0],
                       void_lo=-1, void_hi=0.3, ppc=6.5, seed=8, pool_layout=layout)
    s = make_solver(scene, scene.initial_ppc)
    step = 4
    s.sampler.fill(s.pool, s.cur, step, s.n_ring, 0.0, 1)
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
        ring = np.argwhere(s.regions.ring.to_numpy()[e]) - 1
        assert {tuple(c) for c in origin} <= {tuple(c) for c in ring}
        for c in ring:
            lam = 3.5 if c[0] < 0 else ppc[(e, *c)]
            m = (origin == c).all(axis=1).sum()
            assert np.floor(lam) <= m <= np.ceil(lam)
            k = ids[(origin == c).all(axis=1), 0] & ((1 << bits) - 1)
            assert sorted(k) == list(range(m))  # indices 0 … m − 1 within the cell
