"""The pointer pool (``ti_dk/pools/blocks.py``) through its interface, and so its parts
(``block_memory.py``, ``block_moves.py``): moves between blocks (scan, periodic wrap), growth,
release, and the refusal of what Taichi cannot hold."""
import numpy as np
import pytest
import taichi as ti

from ti_dk import pools
from ti_dk.pools import BlockPool


def _grid(cells, boundary="periodic"):
    from ti_dk import load_scene
    from ti_dk.core.grid import Grid
    return Grid.from_scene(load_scene("ellipse2d", cells=cells, boundary=boundary))


@ti.kernel
def _move_all(p: ti.template(), b: ti.i32, y: ti.types.ndarray(), C: ti.types.ndarray()):
    """Every particle of buffer ``b`` to position ``y`` in cell ``C``; those of odd id0 dropped."""
    for u in range(p.units(b)):
        e, U, lo, hi = p.unit(b, u)
        for k in range(lo, hi):
            I = p.index(b, U, k)
            p.x[I] = ti.Vector([y[0], y[1]])
            p.mark(I, p.pid[I][0] % 2 == 0, ti.Vector([e, C[0], C[1]]))


@pytest.mark.parametrize("src,dst", [((7, 9, 7, 9), (8, 8)),  # four blocks into one: the pool must grow
                                     ((23, 24, 4, 7), (0, 5))])  # across the periodic side (3 blocks per axis)
def test_pointer_pool_moves_between_blocks_and_grows(src, dst):
    grid, rng = _grid([24, 24]), np.random.default_rng(5)
    E, k = 2, 60
    cells = np.zeros((E, 24, 24), dtype=bool)
    cells[:, src[0]:src[1], src[2]:src[3]] = True
    cells[:, dst[0], dst[1]] = True
    lo, hi = np.array([src[0], src[2]]), np.array([src[1], src[3]])
    x = (lo + rng.uniform(size=(E, k, 2)) * (hi - lo)) * grid.dx
    pid = np.stack([rng.permutation(10**6)[:E * k].reshape(E, k), np.full((E, k), 7)], axis=-1).astype(np.uint32)
    p = BlockPool(grid, E, 4, ti.f64).restored(x, pid, np.array([k, k - 9]), cells)
    assert p.capacity > 4  # grown on loading
    got_x, got_pid, got_n = p.occupied(0)
    want_x, want_pid, _ = pools.canonical(x, pid, np.array([k, k - 9]))
    assert np.array_equal(got_n, [k, k - 9])
    assert all(np.array_equal(got_pid[e, :got_n[e]], want_pid[e, :got_n[e]]) for e in range(E))
    assert all(np.array_equal(got_x[e, :got_n[e]], want_x[e, :got_n[e]]) for e in range(E))
    y = (np.array(dst) + 0.5) * grid.dx
    p = p.fitted(np.zeros((E, 24, 24)), cells)  # still room: the same pool
    small = BlockPool(grid, E, 4, ti.f64)
    assert small.fitted(np.ones((E, 24, 24)), cells).capacity == pools.capacity(64)  # one block of 8×8 cells
    _move_all(p, 0, y, np.array(dst, dtype=np.int32))
    p, b = p.compacted(0)
    assert b == 1  # into the other buffer
    x1, pid1, n1 = p.occupied(1)
    assert p.capacity >= n1.max()
    for e in range(E):
        even = np.sort(pid[e, :got_n[e], 0][pid[e, :got_n[e], 0] % 2 == 0])
        assert n1[e] == even.size == p.kept.to_numpy()[e]
        assert np.array_equal(pid1[e, :n1[e], 0], even) and np.all(x1[e, :n1[e]] == y)
    keep = np.zeros_like(cells)
    keep[:, dst[0], dst[1]] = True
    p.retain(keep)
    assert p.active.size == E and np.array_equal(p.occupied(1)[2], n1)


def test_pointer_pool_refuses_what_taichi_cannot_hold():
    cells = np.ones((1, 24, 24), dtype=bool)
    with pytest.raises(OverflowError, match="use pool_layout = 'flat'"):
        BlockPool(_grid([24, 24]), 1, 4, ti.f64).fitted(np.full((1, 24, 24), 1e6), cells)
