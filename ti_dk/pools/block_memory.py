"""The sparse memory of a :class:`~.blocks.BlockPool` as the host changes it (:class:`BlockMemory`):
blocks activated and released, the chunks past their particles released, and particles copied in
(from the host, from a smaller pool) and out."""

import numpy as np
import taichi as ti

from ..core.grid import cell_of
from .slots import CHUNK


@ti.data_oriented
class BlockMemory:
    """Which blocks of ``pool`` are active (:attr:`active` on the host, the pool's ``list`` and
    ``listed`` on the device) and what they hold, set from the host."""

    def __init__(self, pool):
        self.pool, self.block_grid = pool, pool.block_grid
        self.active = np.zeros(0, dtype=np.int32)  # the listed keys on the host, ascending

    def _set_list(self, keys: np.ndarray) -> None:
        p = self.pool
        self.active = keys
        full = np.zeros(p.list.shape[0], dtype=np.int32)
        full[:keys.size] = keys
        p.list.from_numpy(full)
        p.listed[None] = keys.size

    def activate(self, keys: np.ndarray) -> None:
        """Activate the blocks of ``keys`` (those not yet active start empty)."""
        fresh = np.setdiff1d(keys, self.active).astype(np.int32)
        if fresh.size:
            self._touch(fresh)
        self._set_list(np.union1d(self.active, keys).astype(np.int32))

    def retain(self, keys: np.ndarray) -> None:
        """Deactivate the blocks not in ``keys`` (they must hold no particle) and release the chunks
        past each block's particles."""
        gone = np.setdiff1d(self.active, keys).astype(np.int32)
        if gone.size:
            self._drop(gone)
        self._set_list(np.intersect1d(self.active, keys).astype(np.int32))
        self._trim()

    @ti.kernel
    def _touch(self, keys: ti.types.ndarray()):
        p = self.pool
        for i in range(keys.shape[0]):
            e, B = keys[i] // self.block_grid.NB, keys[i] % self.block_grid.NB
            for b in ti.static(range(2)):  # activates the block; a reused block starts empty
                p.n[e, B, b] = 0
            p.fixed[e, B] = 0

    @ti.kernel
    def _drop(self, keys: ti.types.ndarray()):
        for i in range(keys.shape[0]):
            ti.deactivate(self.pool.blk, [keys[i] // self.block_grid.NB, keys[i] % self.block_grid.NB])

    @ti.kernel
    def _trim(self):
        """Release the chunks past the occupied slots of each active block's two buffers."""
        p = self.pool
        for u in range(p.listed[None]):
            e, U, _, _ = p.unit(0, u)
            for b in ti.static(range(2)):
                for c in range((p.n[e, U[1], b] + CHUNK - 1) // CHUNK, p.capacity // CHUNK):
                    # explicit casts: without them Taichi warns "Field index not int32" in 3D
                    ti.deactivate(p.chunks, [ti.i32(e), ti.i32(U[1]), b, ti.i32(c)])

    @ti.kernel
    def chunks(self) -> ti.i32:
        """The active chunks of slots."""
        c = 0
        for _ in ti.grouped(self.pool.chunks):
            c += 1
        return c

    @ti.kernel
    def copy(self, old: ti.template()):
        """Everything ``old`` (a smaller pool with the same active blocks) holds, slot for slot."""
        p = self.pool
        for u in range(p.listed[None]):
            e, U, _, _ = p.unit(0, u)
            for b in ti.static(range(2)):
                m = old.n[e, U[1], b]
                p.n[e, U[1], b] = m
                for q in range(ti.min(m, old.capacity)):
                    p.x[e, U[1], b, q] = old.x[e, U[1], b, q]
                    p.pid[e, U[1], b, q] = old.pid[e, U[1], b, q]
                    p.keep[e, U[1], b, q] = old.keep[e, U[1], b, q]
            p.fixed[e, U[1]] = old.fixed[e, U[1]]
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(p.ensemble):
            p.kept[e] = old.kept[e]

    @ti.kernel
    def put(self, x: ti.types.ndarray(), pid: ti.types.ndarray(), n: ti.types.ndarray()):
        """Buffer 0 from the host, each particle in the block of its cell (``BlockPool.restored``);
        sets the pool's ``need`` to the most particles a block was given."""
        p = self.pool
        for u in range(p.listed[None]):
            e, U, _, _ = p.unit(0, u)
            p.n[e, U[1], 0] = 0
        p.need[None] = 0
        for e, i in ti.ndrange(p.ensemble, x.shape[1]):
            if i < n[e]:
                y = ti.Vector([x[e, i, a] for a in ti.static(range(p.dim))])
                C = ti.Vector([cell_of(y[a], p.real(p.grid.dx[a]), p.cells[a]) for a in ti.static(range(p.dim))])
                U = p.unit_of(e, C)
                j = p.append(0, U, 1)
                ti.atomic_max(p.need[None], j + 1)
                if j < p.capacity:
                    p.x[e, U[1], 0, j] = y
                    p.pid[e, U[1], 0, j] = ti.math.uvec2(pid[e, i, 0], pid[e, i, 1])
        for u in range(p.listed[None]):
            e, U, _, _ = p.unit(0, u)
            p.fixed[e, U[1]] = p.n[e, U[1], 0]
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(p.ensemble):
            p.kept[e] = n[e]

    @ti.kernel
    def counts(self, b: ti.i32, out: ti.types.ndarray()):
        """The particles of each active block in buffer ``b``, in the order of :attr:`active`."""
        for u in range(self.pool.listed[None]):
            _, _, _, hi = self.pool.unit(b, u)
            out[u] = hi

    @ti.kernel
    def gather(self, b: ti.i32, start: ti.types.ndarray(), x: ti.types.ndarray(), pid: ti.types.ndarray()):
        """Buffer ``b`` to the host: active block ``u``'s particles to its member's rows from ``start[u]``."""
        p = self.pool
        for u in range(p.listed[None]):
            e, U, lo, hi = p.unit(b, u)
            for q in range(lo, hi):
                for a in ti.static(range(p.dim)):
                    x[e, start[u] + q, a] = p.x[e, U[1], b, q][a]
                for w in ti.static(range(2)):
                    pid[e, start[u] + q, w] = p.pid[e, U[1], b, q][w]
