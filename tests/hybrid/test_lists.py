"""The ghost ring and the cell lists made on the device (hybrid/lists.py) against a brute-force NumPy
reference under every boundary kind: the ring cell by cell from its definition, the lists as
``np.flatnonzero`` gives them (ascending flat indices)."""
import itertools

import numpy as np
import pytest

from ti_dk.core.grid import DIRICHLET, NEUMANN, PERIODIC, Grid
from ti_dk.hybrid.clustering import RegridParams
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
                                            ((5, 4, 6), (_P, _P, _P)),
                                            ((12, 10, 5), (_P, _D, _N))])  # rows over several scan blocks
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
