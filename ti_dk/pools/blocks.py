"""The ``pointer`` layout (:class:`BlockPool`): blocks of cells under a ``ti.root.pointer``; its host
side (activation, sizing, checkpoints) here, its slot access in :mod:`.block_slots` and the moves of
particles between blocks in :mod:`.block_moves`."""

import itertools
import math

import numpy as np
import taichi as ti

from ..core.grid import numpy_dtype
from .block_moves import BlockMoves
from .block_slots import BlockSlots
from .slots import CHUNK, SIDE, SPARSE_MAX, canonical, capacity


@ti.data_oriented
class BlockPool(BlockSlots, BlockMoves):
    """The ``pointer`` layout: a ``ti.root.pointer`` over (member, block of :data:`SIDE` cells per
    axis), each active block holding two buffers of ``capacity`` slots; block ``B`` of member ``e``
    has key ``(e, B)`` (``B``: C-order index of the block) and holds the particles of its cells.
    A buffer's slots are dense arrays of :data:`CHUNK` slots under a second pointer, allocated as
    they fill: a dense array of ``capacity`` slots per block would make every active block as
    large as the fullest.

    Active blocks are those :meth:`fitted` asked for; :meth:`retain` deactivates the rest and
    releases the chunks past each block's particles. A
    particle moves at most one cell per step, so :meth:`mark` records where it goes as one of
    the ``3^dim`` neighbour blocks, and :meth:`compacted` moves the marked particles by per-block
    counts, an exclusive scan at each target block over its neighbours in a fixed order, and a
    scatter: no atomics, no appends.
    """

    def __init__(self, grid, ensemble: int, capacity: int, real):
        capacity = -(-capacity // CHUNK) * CHUNK  # whole chunks
        self.grid, self.ensemble, self.capacity, self.real = grid, ensemble, capacity, real
        self.dim, self.cells = grid.dim, tuple(grid.cells)
        self.cell_ordered = True  # slots are grouped by block of cells: no sort needed for locality
        self.side = SIDE[self.dim]
        self.nb = tuple(-(-m // self.side) for m in self.cells)  # blocks per axis
        self.NB = math.prod(self.nb)
        assert ensemble * self.NB < 2**31, "block keys are 32-bit"
        self.periodic = tuple(lo == 0 for lo, _ in grid.boundary)  # grid.PERIODIC
        self.dirs = list(itertools.product((-1, 0, 1), repeat=self.dim))  # neighbour blocks, code = index
        self.ndirs = len(self.dirs)
        self.slot_bytes = self.dim * np.dtype(numpy_dtype(real)).itemsize + 8 + 1  # x, pid, keep
        fb = ti.FieldsBuilder()
        self.x = ti.Vector.field(self.dim, real)  # positions [length], index (e, B, buffer, slot)
        self.pid = ti.Vector.field(2, ti.u32)  # identity: two words keying the particle's random numbers
        self.keep = ti.field(ti.u8)  # 0: dropped at the next compaction; 1 + k: goes to neighbour block k
        self.n = ti.field(ti.i32)  # occupied slots, index (e, B, buffer)
        self.fixed = ti.field(ti.i32)  # slots the last compaction left in the block, index (e, B)
        self.cnt = ti.field(ti.i32)  # particles marked for neighbour k, index (e, B, k)
        self.off = ti.field(ti.i32)  # their first slot in that neighbour, index (e, B, k)
        blk = fb.pointer(ti.ij, (ensemble, self.NB))
        self.chunks = blk.dense(ti.k, 2).pointer(ti.l, capacity // CHUNK)  # a block's slots, CHUNK at a time
        self.chunks.dense(ti.l, CHUNK).place(self.x, self.pid, self.keep)
        blk.dense(ti.k, 2).place(self.n)
        blk.dense(ti.k, self.ndirs).place(self.cnt, self.off)
        blk.place(self.fixed)
        self.blk = blk
        self.tree = fb.finalize()
        self.kept = ti.field(ti.i32, shape=ensemble)  # particles the last compaction kept, per member
        self.list = ti.field(ti.i32, shape=ensemble * self.NB)  # keys e·NB + B of the active blocks
        self.listed = ti.field(ti.i32, shape=())  # how many
        self.need = ti.field(ti.i32, shape=())  # most particles a block receives in a compaction
        self.active = np.zeros(0, dtype=np.int32)  # the listed keys on the host, ascending

    # -- host -----------------------------------------------------------------------------
    def _per_block(self, a: np.ndarray, reduce) -> np.ndarray:
        """``reduce`` (``np.any``, ``np.sum``) of ``(ensemble, *cells)`` values over each block's
        cells: ``(ensemble, NB)``."""
        pad = [(0, 0)] + [(0, b * self.side - m) for b, m in zip(self.nb, self.cells)]
        c = np.pad(a, pad).reshape(self.ensemble, *[v for b in self.nb for v in (b, self.side)])
        return reduce(c, axis=tuple(range(2, 2 + 2 * self.dim, 2))).reshape(self.ensemble, self.NB)

    def _keys(self, cells: np.ndarray) -> np.ndarray:
        """Keys of the blocks holding any of ``cells`` (``(ensemble, *cells)`` booleans), ascending."""
        return np.flatnonzero(self._per_block(cells, np.any)).astype(np.int32)

    def _set_list(self, keys: np.ndarray) -> None:
        self.active = keys
        full = np.zeros(self.list.shape[0], dtype=np.int32)
        full[:keys.size] = keys
        self.list.from_numpy(full)
        self.listed[None] = keys.size

    @property
    def nbytes(self) -> int:
        """Bytes of the active blocks (counts, scan offsets, chunk pointers) and of their active chunks."""
        block = 4 * (3 + 2 * self.ndirs) + 2 * (self.capacity // CHUNK) * 8
        return self.active.size * block + self._active_chunks() * CHUNK * self.slot_bytes

    def grown(self, capacity: int) -> "BlockPool":
        """This pool, or (when ``capacity`` exceeds its own) a new one with at least ``capacity``
        and at least twice the old slots per block (every new pool recompiles the kernels),
        holding the same blocks and particles; the old pool's memory is released."""
        if capacity <= self.capacity:
            return self
        new = BlockPool(self.grid, self.ensemble, max(capacity, 2 * self.capacity), self.real)
        new._activate(self.active)
        new._copy(self)
        self.tree.destroy()
        return new

    def fitted(self, need: np.ndarray, cells: np.ndarray) -> "BlockPool":
        """A pool whose blocks holding ``cells`` (``(ensemble, *cells)`` booleans) are active, and
        with room in every block for ``need`` (``(ensemble, *cells)``: slots each cell may ask for)."""
        keys = self._keys(cells)
        most = float(self._per_block(need, np.sum).max()) if need.size else 0.0
        slots = 2 * (float(need.sum()) + CHUNK * keys.size)  # both buffers, a partial chunk per block
        if slots * self.slot_bytes > SPARSE_MAX:
            raise OverflowError(
                f"pool_layout = 'pointer' would plan for {slots * self.slot_bytes / 2**30:.2g} GiB of particles, more "
                f"than the {SPARSE_MAX / 2**30:g} GiB it allows (Taichi's CPU runtime crashes on sparse data of about "
                "1.5 GiB): use pool_layout = 'flat'")
        new = self.grown(capacity(most))
        new._activate(keys)
        return new

    def _activate(self, keys: np.ndarray) -> None:
        fresh = np.setdiff1d(keys, self.active).astype(np.int32)
        if fresh.size:
            self._touch(fresh)
        self._set_list(np.union1d(self.active, keys).astype(np.int32))

    def retain(self, cells: np.ndarray) -> None:
        """Deactivate the blocks that hold none of ``cells`` (they must hold no particle)."""
        keys = self._keys(cells)
        gone = np.setdiff1d(self.active, keys).astype(np.int32)
        if gone.size:
            self._drop(gone)
        self._set_list(np.intersect1d(self.active, keys).astype(np.int32))
        self._trim()

    def compacted(self, b: int) -> tuple["BlockPool", int]:
        """The marked slots of buffer ``b`` moved, in order, to the front of their target blocks in
        the other buffer; a larger pool first when a block would overflow. Returns the pool and
        the buffer that holds the particles (the other one)."""
        pool = self
        while True:
            pool._scan(b)
            need = int(pool.need[None])
            if need <= pool.capacity:
                break
            pool = pool.grown(need)
        pool._scatter(b)
        return pool, 1 - b

    def restored(self, x: np.ndarray, pid: np.ndarray, n: np.ndarray, cells: np.ndarray) -> "BlockPool":
        """A pool holding ``x``, ``pid`` (``(ensemble, slots, …)``, member ``e`` in its first ``n[e]``
        slots) in buffer 0, each in the block of its cell, the blocks of ``cells`` active."""
        x = np.ascontiguousarray(x, dtype=numpy_dtype(self.real))
        pid = np.ascontiguousarray(pid, dtype=np.uint32)
        n = np.ascontiguousarray(n, dtype=np.int32)
        pool = self
        pool._activate(pool._keys(cells))
        while True:
            pool._put(x, pid, n)
            need = int(pool.need[None])
            if need <= pool.capacity:
                return pool
            pool = pool.grown(need)

    def occupied(self, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Buffer ``b`` on the host, as :meth:`ParticlePool.occupied`: ``(ensemble, max n, …)``
        positions and identities, each member's sorted by :func:`canonical`, and ``n``."""
        k = self.active.size
        counts = np.zeros(max(k, 1), dtype=np.int32)
        self._counts(b, counts)
        members = self.active // self.NB
        n = np.bincount(members, weights=counts[:k], minlength=self.ensemble).astype(np.int32)
        start = np.zeros(max(k, 1), dtype=np.int32)  # first slot of each block in its member's rows
        for e in range(self.ensemble):
            sel = np.flatnonzero(members == e)
            start[sel] = np.cumsum(counts[sel]) - counts[sel]
        top = max(1, int(n.max()) if n.size else 1)
        x = np.zeros((self.ensemble, top, self.dim), dtype=numpy_dtype(self.real))
        pid = np.zeros((self.ensemble, top, 2), dtype=np.uint32)
        self._gather(b, start, x, pid)
        return canonical(x, pid, n)
