"""The particle region: ghost ring and cell lists against a brute-force NumPy reference under every
boundary kind, and independence of the box layout (one ghost set per cell)."""
import itertools

import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.control.registry import make_solver
from ti_dk.core.grid import DIRICHLET, NEUMANN, PERIODIC, Grid
from ti_dk.hybrid.clustering import RegridParams, mask
from ti_dk.hybrid.region import Region


def _ring_reference(covered, boundary):
    """Ghost cells on the padded grid, cell by cell from the definition."""
    E, *n = covered.shape
    ring = np.zeros((E, *(m + 2 for m in n)), dtype=np.uint8)
    for e, *P in itertools.product(*(range(s) for s in ring.shape)):
        C = [p - 1 for p in P]
        out = [(a, 0 if c < 0 else 1) for a, c in enumerate(C) if not 0 <= c < n[a]]
        if len(out) > 1 or any(boundary[a][s] != DIRICHLET for a, s in out):
            continue
        if not out and covered[(e, *C)]:
            continue
        for off in itertools.product((-1, 0, 1), repeat=len(n)):
            N = [c + o for c, o in zip(C, off)]
            N = [x % m if boundary[a][0] == PERIODIC else x for a, (x, m) in enumerate(zip(N, n))]
            if all(0 <= x < m for x, m in zip(N, n)) and covered[(e, *N)]:
                ring[(e, *P)] = 1
    return ring


_P, _D, _N = (PERIODIC, PERIODIC), (DIRICHLET, DIRICHLET), (NEUMANN, NEUMANN)


@pytest.mark.parametrize("cells,boundary", [((7, 6), (_P, _P)), ((7, 6), ((DIRICHLET, NEUMANN), _P)),
                                            ((7, 6), (_D, (NEUMANN, DIRICHLET))), ((9,), (_D,)), ((9,), (_P,)),
                                            ((5, 4, 6), ((DIRICHLET, NEUMANN), _P, (NEUMANN, DIRICHLET))),
                                            ((5, 4, 6), (_P, _P, _P))])
def test_ring_and_lists_match_the_definition(cells, boundary):
    d = len(cells)
    grid = Grid(cells, (1.0,) * d, boundary, ((2.0, 3.0),) * d)
    r = Region(grid, 3, RegridParams())
    covered = (np.random.default_rng(1).uniform(size=(3, *cells)) < 0.2).astype(np.uint8)
    covered[1, 0] = 1  # a whole boundary layer: reservoir ghosts below it
    r.load_state({"covered": covered, "boxes": np.zeros((0, 1 + 2 * d), dtype=np.int64)})  # and lists()
    ring = r.ring_mask.astype(np.uint8)
    assert np.array_equal(ring, _ring_reference(covered, boundary))
    # the lists: flat indices, ascending (the order every loop over them keeps)
    assert r.n_ring == ring.sum() and r.n_cover == covered.sum()
    assert np.array_equal(r.ring_list.to_numpy()[:r.n_ring], np.flatnonzero(ring))
    assert np.array_equal(r.cover_list.to_numpy()[:r.n_cover], np.flatnonzero(covered))


def test_box_layout_does_not_matter_and_shared_ghosts_are_sampled_once():
    scene = load_scene("equilibrium1d", method="hybrid", cells=[16, 16], regrid_interval=0, threshold=1, ppc=3,
                       t_equil=None, histogram=None, seed=7, ensemble=1)
    one = [((2, 2), (7, 12)), ((8, 2), (12, 12))]  # two boxes with a one-cell gap (x = 7) between them
    other = [((2, 2), (5, 7)), ((2, 7), (7, 12)), ((5, 2), (7, 7)), ((8, 2), (12, 5)), ((8, 5), (12, 12))]
    assert np.array_equal(mask(one, (16, 16)), mask(other, (16, 16)))
    final = []
    for boxes in (one, other):
        s = make_solver(scene, scene.initial_ppc)
        s.set_region(mask(boxes, (16, 16))[None], 0)
        # 3 particles per cell everywhere: the ghost ring gets exactly 3 per ghost cell, once each,
        # the gap column included although it borders both boxes
        s.sampler.fill(s.pool, s.cur, 0, s.n_ring, 0.0, 1, 0)
        n_ghost = s.pool.n.to_numpy()[s.cur, 0] - s.n_real.to_numpy()[0]
        assert n_ghost == 3 * s.regions.ring_mask.sum() == 3 * (12 * 12 - 9 * 10)
        for n in range(30):
            s.step(n)
        final.append(s.density())
    assert np.array_equal(final[0], final[1])
