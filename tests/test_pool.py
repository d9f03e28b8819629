"""The particle pool: compaction against NumPy (order kept, across block edges), growth that keeps
the particles, and the one capacity rule against Poisson fluctuations."""
import math

import numpy as np
import taichi as ti

from ti_dk import pool
from ti_dk.pool import BLOCK, ParticlePool


def _filled(E, cap, n, rng):
    p = ParticlePool(E, cap, 2, ti.f64)
    x = rng.uniform(size=(2, E, cap, 2))
    pid = rng.integers(0, 2**32, size=(2, E, cap, 2), dtype=np.uint32)
    p.load(x, pid, np.stack([n, np.zeros_like(n)]))
    return p, x, pid


def test_compaction_keeps_the_marked_slots_in_order():
    rng = np.random.default_rng(3)
    E, cap = 3, 3 * BLOCK + 17  # several blocks, the last one partial
    n = np.array([cap, 0, BLOCK + 1])
    p, x, pid = _filled(E, cap, n, rng)
    keep = (rng.uniform(size=(E, cap)) < 0.4).astype(np.uint8)
    p.keep.from_numpy(keep)
    p.compact(0)
    got_x, got_pid, got_n = p.occupied(1)
    for e in range(E):
        want = np.flatnonzero(keep[e, :n[e]])
        assert got_n[e] == want.size == p.kept.to_numpy()[e]
        assert np.array_equal(got_x[e, :want.size], x[0, e, want])
        assert np.array_equal(got_pid[e, :want.size], pid[0, e, want])
    p.n.from_numpy(np.stack([n, got_n]).astype(np.int32))
    p.truncate(0)  # drop what was appended after the compaction
    assert np.array_equal(p.n.to_numpy()[0], got_n)


def test_growth_keeps_the_particles():
    rng = np.random.default_rng(4)
    n = np.array([5, 9])
    p, x, pid = _filled(2, 10, n, rng)
    assert p.grown(10) is p
    q = p.grown(13)
    assert q.capacity == 20  # at least twice: every new pool recompiles its kernels
    qx, qpid, qn = q.occupied(0)
    assert np.array_equal(qn, n) and np.array_equal(qx, x[0, :, :9]) and np.array_equal(qpid, pid[0, :, :9])


def test_capacity_rule_holds_poisson_fluctuations():
    for need in (0, 1, 10, 1e3, 1e6):
        c = pool.capacity(need)
        assert c >= need + 4 * math.sqrt(need) + 64 and c <= 1.5 * need + 4 * math.sqrt(need) + 64
