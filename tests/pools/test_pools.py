"""The particle pools: the members' total, compaction against NumPy (in place, ranks across block edges), settling what was
appended, growth that keeps the particles, the one capacity rule against Poisson fluctuations, and
the pointer layout's moves between blocks (scan, periodic wrap, growth, release)."""
import math

import numpy as np
import pytest
import taichi as ti

from ti_dk import pools
from ti_dk.pools import BLOCK, BlockPool, ParticlePool


def _filled(E, cap, n, rng):
    p = ParticlePool(E, cap, 2, ti.f64)
    x = rng.uniform(size=(2, E, cap, 2))
    pid = rng.integers(0, 2**32, size=(2, E, cap, 2), dtype=np.uint32)
    p.load(x, pid, np.stack([n, np.zeros_like(n)]))
    return p, x, pid


@pytest.mark.parametrize("E", [3, 40])  # read one by one, and copied at once
def test_total_sums_a_row_of_member_counts(E):
    counts = ti.field(ti.i32, shape=(2, E))
    values = np.random.default_rng(E).integers(0, 2**30, size=(2, E), dtype=np.int32)
    counts.from_numpy(values)
    assert pools.total(counts, (1,)) == values[1].sum(dtype=np.int64)
    assert pools.total(counts, (0,)) == values[0].sum(dtype=np.int64)


def test_compaction_fills_the_holes_with_the_last_marked_slots_in_place():
    rng = np.random.default_rng(3)
    E, cap = 5, 3 * BLOCK + 17  # several blocks, the last one partial
    n = np.array([cap, 0, BLOCK + 1, 2 * BLOCK, 2 * BLOCK])
    p, x, pid = _filled(E, cap, n, rng)
    keep = (rng.uniform(size=(E, cap)) < 0.4).astype(np.uint8)
    keep[3] = 1  # all marked: nothing moves (the kept count ends a block)
    keep[4, :BLOCK + 3] = 1  # the kept count inside a block whose start lies below it
    p.keep.from_numpy(keep)
    assert p.compacted(0) == (p, 0)
    got_x, got_pid, got_n = p.x.to_numpy()[0], p.pid.to_numpy()[0], p.n.to_numpy()[0]  # occupied() would sort
    for e in range(E):
        marked = keep[e, :n[e]].astype(bool)
        k = int(marked.sum())
        holes, tails = np.flatnonzero(~marked[:k]), k + np.flatnonzero(marked[k:])
        want_x, want_pid = x[0, e, :k].copy(), pid[0, e, :k].copy()
        want_x[holes], want_pid[holes] = x[0, e, tails], pid[0, e, tails]  # the i-th hole takes the i-th tail
        assert got_n[e] == k == p.kept.to_numpy()[e]
        assert np.array_equal(got_x[e, :k], want_x) and np.array_equal(got_pid[e, :k], want_pid)
    p.n.from_numpy(np.stack([n, got_n]).astype(np.int32))
    p.truncate(0)  # drop what was appended after the compaction
    assert np.array_equal(p.n.to_numpy()[0], got_n)
    p.n.from_numpy(np.stack([n, got_n]).astype(np.int32))  # appended again: settle keeps them where they lie
    p.settle(0)
    p.truncate(0)
    assert np.array_equal(p.kept.to_numpy(), n) and np.array_equal(p.n.to_numpy()[0], n)


def test_growth_keeps_the_particles():
    rng = np.random.default_rng(4)
    n = np.array([5, 9])
    p, x, pid = _filled(2, 10, n, rng)
    assert p.grown(10) is p
    q = p.grown(13)
    assert q.capacity == 20  # at least twice: every new pool recompiles its kernels
    assert q.grown(36).capacity == 45  # and a quarter more than asked
    qx, qpid, qn = q.occupied(0)
    want_x, want_pid, _ = pools.canonical(x[0, :, :9], pid[0, :, :9], n)  # occupied(): sorted by identity
    assert np.array_equal(qn, n)
    for e in range(2):
        assert np.array_equal(qx[e, :n[e]], want_x[e, :n[e]]) and np.array_equal(qpid[e, :n[e]], want_pid[e, :n[e]])


def test_capacity_rule_holds_poisson_fluctuations():
    for need in (0, 1, 10, 1e3, 1e6):
        c = pools.capacity(need)
        assert c >= need + 4 * math.sqrt(need) + 64 and c <= 1.5 * need + 4 * math.sqrt(need) + 64


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
