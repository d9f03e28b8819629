"""Particle storage shared by the particle method and the hybrid: slots per member, growth,
one order-keeping compaction and one capacity rule."""

import math

import numpy as np
import taichi as ti

from .grid import numpy_dtype

BLOCK = 256  # slots per compaction block: an exclusive scan over blocks replaces a contended atomic


def capacity(need: float) -> int:
    """Slots for a member that may come to hold ``need`` particles while particles enter and
    leave (Dirichlet reservoirs, a hybrid's ghosts and regrids): half as many again, four Poisson
    standard deviations (√need) and 64 for a nearly empty member. A member whose particles
    cannot change in number needs exactly its count and no headroom."""
    return int(1.5 * need + 4 * math.sqrt(need) + 64)


@ti.data_oriented
class ParticlePool:
    """The particles of every member: buffer ``b`` of member ``e`` holds slots ``[0, n[b, e])``.

    With ``buffers = 2`` a step reads one buffer, marks the slots to ``keep`` and :meth:`compact`
    copies them, in order, to the front of the other; a member that needs more than
    ``capacity`` slots gets a larger pool from :meth:`grown`. With ``ids`` every particle carries
    its identity (two words that key its random numbers; otherwise the slot is the identity).
    """

    def __init__(self, ensemble: int, capacity: int, dim: int, real, buffers: int = 2, ids: bool = True):
        self.ensemble, self.capacity, self.dim, self.real = ensemble, capacity, dim, real
        self.buffers, self.ids = buffers, ids
        self.blocks = -(-capacity // BLOCK)  # compaction blocks per member
        self.x = ti.Vector.field(dim, real, shape=(buffers, ensemble, capacity))  # positions [length]
        if ids:  # identity: two words keying the particle's random numbers (solver-defined)
            self.pid = ti.Vector.field(2, ti.u32, shape=(buffers, ensemble, capacity))
        self.n = ti.field(ti.i32, shape=(buffers, ensemble))  # occupied slots per buffer and member
        self.kept = ti.field(ti.i32, shape=ensemble)  # slots the last compaction kept, per member
        self.top = ti.field(ti.i32, shape=())  # most occupied slots of any member (set by occupied())
        if buffers == 2:
            self.keep = ti.field(ti.u8, shape=(ensemble, capacity))  # 1: the slot survives the compaction
            self.offset = ti.field(ti.i32, shape=(ensemble, self.blocks))  # first target slot of each block

    def grown(self, capacity: int) -> "ParticlePool":
        """This pool, or (when ``capacity`` exceeds its own) a new one of at least ``capacity`` slots
        and at least twice the old (every new pool recompiles the kernels) holding the same particles."""
        if capacity <= self.capacity:
            return self
        capacity = max(capacity, 2 * self.capacity)
        new = ParticlePool(self.ensemble, capacity, self.dim, self.real, self.buffers, self.ids)
        new.load(self.x.to_numpy(), self.pid.to_numpy() if self.ids else None, self.n.to_numpy())
        new.kept.from_numpy(self.kept.to_numpy())
        return new

    def load(self, x: np.ndarray, pid: np.ndarray | None, n: np.ndarray) -> None:
        """Fill from host arrays ``(b, ensemble, slots, …)`` of at most ``buffers`` buffers and
        ``capacity`` slots (``n``: ``(buffers, ensemble)``); everything else is zeroed."""
        b, k = x.shape[0], x.shape[2]
        px = np.zeros((self.buffers, self.ensemble, self.capacity, self.dim), dtype=numpy_dtype(self.real))
        px[:b, :, :k] = x
        self.x.from_numpy(px)
        if self.ids:
            ppid = np.zeros((self.buffers, self.ensemble, self.capacity, 2), dtype=np.uint32)
            ppid[:b, :, :k] = pid
            self.pid.from_numpy(ppid)
        self.n.from_numpy(np.ascontiguousarray(n, dtype=np.int32))

    def occupied(self, b: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Buffer ``b`` on the host: positions and identities of slots ``[0, max n)``, and ``n``."""
        n = self.n.to_numpy()[b]
        top = max(1, int(n.max()))
        return self.x.to_numpy()[b, :, :top], self.pid.to_numpy()[b, :, :top] if self.ids else None, n

    # -- device ---------------------------------------------------------------------------
    @ti.func
    def find_top(self, b):
        """Set :attr:`top` to the most occupied slots of any member in buffer ``b`` (for
        :meth:`slot`; a loop over the occupied slots only, not the whole capacity)."""
        self.top[None] = 0
        for e in range(self.ensemble):
            ti.atomic_max(self.top[None], self.n[b, e])

    @ti.func
    def slot(self, i):
        """Member and slot of flat index ``i`` in ``[0, ensemble · top)``."""
        e, p = 0, i
        if ti.static(self.ensemble > 1):
            e, p = i // self.top[None], i % self.top[None]
        return e, p

    @ti.kernel
    def compact(self, b: ti.i32):
        """Copy the slots of buffer ``b`` marked in :attr:`keep` to the front of the other buffer,
        in order (per-block counts, an exclusive scan over blocks, a scatter); :attr:`kept` and
        the other buffer's ``n`` get the count."""
        nxt = 1 - b
        for e, k in ti.ndrange(self.ensemble, self.blocks):
            c = 0
            for p in range(k * BLOCK, ti.min(k * BLOCK + BLOCK, self.n[b, e])):
                c += ti.cast(self.keep[e, p], ti.i32)
            self.offset[e, k] = c
        for e in range(self.ensemble):
            total = 0
            for k in range(self.blocks):
                c = self.offset[e, k]
                self.offset[e, k] = total
                total += c
            self.n[nxt, e] = total
            self.kept[e] = total
        for e, k in ti.ndrange(self.ensemble, self.blocks):
            j = self.offset[e, k]
            for p in range(k * BLOCK, ti.min(k * BLOCK + BLOCK, self.n[b, e])):
                if self.keep[e, p]:
                    self.x[nxt, e, j] = self.x[b, e, p]
                    if ti.static(self.ids):
                        self.pid[nxt, e, j] = self.pid[b, e, p]
                    j += 1

    @ti.kernel
    def truncate(self, b: ti.i32):
        """Drop what was appended to buffer ``b`` since the last compaction."""
        for e in range(self.ensemble):
            self.n[b, e] = self.kept[e]
