"""A move's sums on the device (hybrid/tally.py) against NumPy: the slots the pool must offer, the
content the move covers anew, the cells it uncovers, the members it moves, and each cell's slots."""
import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.control.registry import make_solver
from ti_dk.hybrid import clustering


@pytest.mark.parametrize("cells,boundary", [((30,), "periodic"), ((12, 9), "neumann"), ((7, 6, 9), "periodic"),
                                            ((6, 8, 5), ["periodic", "neumann", "neumann"])])
def test_the_sums_are_numpys(cells, boundary):
    scene = load_scene("void1d", method="hybrid", cells=list(cells), boundary=boundary, ensemble=3,
                       regrid_interval=0, seed=1)
    s = make_solver(scene, scene.initial_ppc)
    rng = np.random.default_rng(len(cells))
    content = rng.uniform(-2, 9, size=(3, *cells))
    old = rng.uniform(size=(3, *cells)) < 0.3
    target = rng.uniform(size=(3, *cells)) < 0.2
    target[1] = False  # a member with no target: its covered cells only
    s.spde.q.from_numpy(content / s.grid.cell_volume)
    s.regions.covered.from_numpy(old.astype(np.uint8))
    tally = s.regridder.tally
    tally.aim(target)
    most, removed, gone, members = tally.count(s.spde)
    near = old | clustering.grow(target, 1, (None, *s.regions.periodic))
    want = np.where(near, np.ceil(np.maximum(content, 0)), 0.0)
    assert most == pytest.approx(want.reshape(3, -1).sum(axis=1).max(), rel=1e-12)
    assert removed == pytest.approx(content[target & ~old].sum(), rel=1e-12)
    assert gone == (old & ~target).sum() and members == (old != target).reshape(3, -1).any(axis=1).sum()
    assert np.array_equal(tally.per_cell(s.spde), want)
    tally.aim(old)  # a move that moves nothing
    assert tally.count(s.spde)[1:] == (0.0, 0, 0)
