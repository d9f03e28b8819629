"""The flat pool (``ti_dk/pools/flat.py``): compaction against NumPy (in place, ranks across block
edges), settling what was appended, growth that keeps the particles."""
import numpy as np
import taichi as ti

from ti_dk import pools
from ti_dk.pools import BLOCK, ParticlePool


def _filled(E, cap, n, rng):
    p = ParticlePool(E, cap, 2, ti.f64)
    x = rng.uniform(size=(2, E, cap, 2))
    pid = rng.integers(0, 2**32, size=(2, E, cap, 2), dtype=np.uint32)
    p.load(x, pid, np.stack([n, np.zeros_like(n)]))
    return p, x, pid


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
