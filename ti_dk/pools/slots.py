"""The rules every particle pool follows: slots per compaction block, the layouts, how many slots a
member gets (:func:`capacity`), the particle total, and the order a checkpoint stores."""

import math

import numpy as np


# slots per compaction block (an exclusive scan over blocks replaces a contended atomic) and per
# unit of the particle loops: small, so that a loop has the ≥ 1024 units two threads need (units)
BLOCK = 32
LAYOUTS = ("flat", "pointer")  # the scene key pool_layout
SIDE = {1: 32, 2: 8, 3: 8}  # cells per axis of a pointer block, by dimension (benchmarks/RESULTS.md)
CHUNK = 64  # slots per chunk of a pointer block's array: allocated as it fills, released at regrids
# bytes of particle chunks a pointer pool may plan for (both buffers): Taichi 1.7.4's CPU runtime
# dies with a segfault once its sparse nodes hold about 1.5-2 GiB (sphere3d at 200^3; alone: 60,000
# pointer blocks of 14 chunks of 64 slots), so a larger run is refused with a message instead
SPARSE_MAX = 1 << 30


def capacity(need: float) -> int:
    """Slots for a member that may come to hold ``need`` particles while particles enter and
    leave (Dirichlet reservoirs, a hybrid's ghosts and regrids): half as many again, four Poisson
    standard deviations (√need) and 64 for a nearly empty member. A member whose particles
    cannot change in number needs exactly its count and no headroom."""
    return int(1.5 * need + 4 * math.sqrt(need) + 64)


def total(counts, row: tuple = ()) -> int:
    """Σ of the per-member counts ``counts[(*row, e)]`` (an i32 field whose last axis is the
    member): the particles a solver reports after every step. A few members are read one by
    one; many are copied at once (``to_numpy`` launches a kernel whose parallel task costs more
    than a few single reads)."""
    E = counts.shape[-1]
    if E <= 16:
        return sum(int(counts[(*row, e)]) for e in range(E))
    return int(counts.to_numpy()[row].sum(dtype=np.int64))


def canonical(x: np.ndarray, pid: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each member's first ``n[e]`` particles sorted by identity (birth word, then ``id0``) and the
    slots after them zeroed: the content of a checkpoint, whatever the layout or the thread order
    that appended them."""
    x, pid = x.copy(), pid.copy()
    for e, k in enumerate(n):
        order = np.lexsort((pid[e, :k, 0], pid[e, :k, 1]))
        x[e, :k], pid[e, :k] = x[e, order], pid[e, order]
        x[e, k:], pid[e, k:] = 0, 0
    return x, pid, n
