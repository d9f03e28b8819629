"""The ``pointer`` layout (:class:`BlockPool`): blocks of cells under a ``ti.root.pointer``. The pool
holds the fields and the hybrid's access to its slots, and is made of three parts, each an object of
its own: the blocks over the grid (:class:`~.block_grid.BlockGrid`), the sparse memory set from the
host (:class:`~.block_memory.BlockMemory`) and the moves of particles between blocks at a
compaction (:class:`~.block_moves.BlockMoves`)."""

import numpy as np
import taichi as ti

from ..core.grid import numpy_dtype
from .block_grid import BlockGrid
from .block_memory import BlockMemory
from .block_moves import BlockMoves
from .slots import CHUNK, SPARSE_MAX, canonical, capacity


@ti.data_oriented
class BlockPool:
    """The ``pointer`` layout: a ``ti.root.pointer`` over (member, block of ``SIDE`` cells per
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
        self.by_cell = True  # plans its room per block: fitted() takes each cell's need
        self.in_place = False  # compacts into the other buffer, growing first where a block would overflow
        self.block_grid = g = BlockGrid(grid, ensemble)
        self.slot_bytes = self.dim * np.dtype(numpy_dtype(real)).itemsize + 8 + 1  # x, pid, keep
        fb = ti.FieldsBuilder()
        self.x = ti.Vector.field(self.dim, real)  # positions [length], index (e, B, buffer, slot)
        self.pid = ti.Vector.field(2, ti.u32)  # identity: two words keying the particle's random numbers
        self.keep = ti.field(ti.u8)  # 0: dropped at the next compaction; 1 + k: goes to neighbour block k
        self.n = ti.field(ti.i32)  # occupied slots, index (e, B, buffer)
        self.fixed = ti.field(ti.i32)  # slots the last compaction left in the block, index (e, B)
        self.cnt = ti.field(ti.i32)  # particles marked for neighbour k, index (e, B, k)
        self.off = ti.field(ti.i32)  # their first slot in that neighbour, index (e, B, k)
        blk = fb.pointer(ti.ij, (ensemble, g.NB))
        self.chunks = blk.dense(ti.k, 2).pointer(ti.l, capacity // CHUNK)  # a block's slots, CHUNK at a time
        self.chunks.dense(ti.l, CHUNK).place(self.x, self.pid, self.keep)
        blk.dense(ti.k, 2).place(self.n)
        blk.dense(ti.k, g.ndirs).place(self.cnt, self.off)
        blk.place(self.fixed)
        self.blk = blk
        self.tree = fb.finalize()
        self.kept = ti.field(ti.i32, shape=ensemble)  # particles the last compaction kept, per member
        self.list = ti.field(ti.i32, shape=ensemble * g.NB)  # keys e·NB + B of the active blocks
        self.listed = ti.field(ti.i32, shape=())  # how many
        self.need = ti.field(ti.i32, shape=())  # most particles a block receives in a compaction
        self.memory, self.moves = BlockMemory(self), BlockMoves(self)

    # -- host -----------------------------------------------------------------------------
    @property
    def active(self) -> np.ndarray:
        """The keys ``e·NB + B`` of the active blocks, ascending."""
        return self.memory.active

    @property
    def nbytes(self) -> int:
        """Bytes of the active blocks (counts, scan offsets, chunk pointers) and of their active chunks."""
        block = 4 * (3 + 2 * self.block_grid.ndirs) + 2 * (self.capacity // CHUNK) * 8
        return self.active.size * block + self.memory.chunks() * CHUNK * self.slot_bytes

    def grown(self, capacity: int) -> "BlockPool":
        """This pool, or (when ``capacity`` exceeds its own) a new one with at least ``capacity``
        and at least twice the old slots per block (every new pool recompiles the kernels),
        holding the same blocks and particles; the old pool's memory is released."""
        if capacity <= self.capacity:
            return self
        new = BlockPool(self.grid, self.ensemble, max(capacity, 2 * self.capacity), self.real)
        new.memory.activate(self.active)
        new.memory.copy(self)
        self.tree.destroy()
        return new

    def fitted(self, need: np.ndarray, cells: np.ndarray) -> "BlockPool":
        """A pool whose blocks holding ``cells`` (``(ensemble, *cells)`` booleans) are active, and
        with room in every block for ``need`` (``(ensemble, *cells)``: slots each cell may ask for)."""
        keys = self.block_grid.keys(cells)
        most = float(self.block_grid.per_block(need, np.sum).max()) if need.size else 0.0
        slots = 2 * (float(need.sum()) + CHUNK * keys.size)  # both buffers, a partial chunk per block
        if slots * self.slot_bytes > SPARSE_MAX:
            raise OverflowError(
                f"pool_layout = 'pointer' would plan for {slots * self.slot_bytes / 2**30:.2g} GiB of particles, more "
                f"than the {SPARSE_MAX / 2**30:g} GiB it allows (Taichi's CPU runtime crashes on sparse data of about "
                "1.5 GiB): use pool_layout = 'flat'")
        new = self.grown(capacity(most))
        new.memory.activate(keys)
        return new

    def retain(self, cells: np.ndarray) -> None:
        """Deactivate the blocks that hold none of ``cells`` (they must hold no particle)."""
        self.memory.retain(self.block_grid.keys(cells))

    def compacted(self, b: int) -> tuple["BlockPool", int]:
        """The marked slots of buffer ``b`` moved, in order, to the front of their target blocks in
        the other buffer; a larger pool first when a block would overflow. Returns the pool and
        the buffer that holds the particles (the other one)."""
        pool = self
        while True:
            pool.moves.scan(b)
            need = int(pool.need[None])
            if need <= pool.capacity:
                break
            pool = pool.grown(need)
        pool.moves.scatter(b)
        return pool, 1 - b

    def restored(self, x: np.ndarray, pid: np.ndarray, n: np.ndarray, cells: np.ndarray) -> "BlockPool":
        """A pool holding ``x``, ``pid`` (``(ensemble, slots, …)``, member ``e`` in its first ``n[e]``
        slots) in buffer 0, each in the block of its cell, the blocks of ``cells`` active."""
        x = np.ascontiguousarray(x, dtype=numpy_dtype(self.real))
        pid = np.ascontiguousarray(pid, dtype=np.uint32)
        n = np.ascontiguousarray(n, dtype=np.int32)
        pool = self
        pool.memory.activate(pool.block_grid.keys(cells))
        while True:
            pool.memory.put(x, pid, n)
            need = int(pool.need[None])
            if need <= pool.capacity:
                return pool
            pool = pool.grown(need)

    def occupied(self, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Buffer ``b`` on the host, as :meth:`ParticlePool.occupied`: ``(ensemble, max n, …)``
        positions and identities, each member's sorted by :func:`canonical`, and ``n``."""
        k = self.active.size
        counts = np.zeros(max(k, 1), dtype=np.int32)
        self.memory.counts(b, counts)
        members = self.active // self.block_grid.NB
        n = np.bincount(members, weights=counts[:k], minlength=self.ensemble).astype(np.int32)
        start = np.zeros(max(k, 1), dtype=np.int32)  # first slot of each block in its member's rows
        for e in range(self.ensemble):
            sel = np.flatnonzero(members == e)
            start[sel] = np.cumsum(counts[sel]) - counts[sel]
        top = max(1, int(n.max()) if n.size else 1)
        x = np.zeros((self.ensemble, top, self.dim), dtype=numpy_dtype(self.real))
        pid = np.zeros((self.ensemble, top, 2), dtype=np.uint32)
        self.memory.gather(b, start, x, pid)
        return canonical(x, pid, n)

    # -- the hybrid's interface (see the module docstring of ti_dk.pools) -----------------------
    @ti.func
    def assume_active(self):
        """Let the calling kernel reach a block's own fields without activating it (a write to a
        pointer SNode otherwise checks for an active cell first). Every block a kernel of the
        hybrid touches is active, made so by :meth:`fitted`; only ``BlockMemory.activate``
        activates blocks. Chunks of slots are activated by the writes that fill them."""
        ti.no_activate(self.n, self.cnt, self.off, self.fixed)

    @ti.func
    def units(self, b):
        """Units of the particle loop (over either buffer): the active blocks."""
        return self.listed[None]

    @ti.func
    def unit(self, b, u):
        """Member, key and occupied slot range ``[lo, hi)`` of active block ``u`` in buffer ``b``."""
        key = self.list[u]
        e = key // self.block_grid.NB
        U = ti.Vector([e, key % self.block_grid.NB])
        return e, U, 0, self.n[U[0], U[1], b]

    @ti.func
    def split_unit(self, b, u):
        """:meth:`unit` with its slots cut at ``mid``: ``(e, U, lo, mid, hi)``, ``[lo, mid)`` held since
        the last compaction, ``[mid, hi)`` appended since (:meth:`new_unit`)."""
        e, U, lo, hi = self.unit(b, u)
        return e, U, lo, self.fixed[U[0], U[1]], hi

    @ti.func
    def unit_of(self, e, C):
        """The key of the block of cell ``C`` of member ``e`` (a reservoir cell: the boundary block)."""
        return ti.Vector([e, self.block_grid.block_of(C)])

    @ti.func
    def new_units(self, b):
        """Units of a loop over the slots appended to buffer ``b`` since the last compaction:
        every active block (:meth:`new_unit` gives each its appended range)."""
        return self.units(b)

    @ti.func
    def new_unit(self, b, u):
        """Member, key and range ``[lo, hi)`` of the slots of block ``u`` appended since the last compaction."""
        e, U, _lo, hi = self.unit(b, u)
        return e, U, self.fixed[U[0], U[1]], hi

    @ti.func
    def index(self, b, U, p):
        """The slot ``p`` of block ``U`` (member, key) in buffer ``b``, as a field index."""
        return ti.Vector([U[0], U[1], b, p])

    @ti.func
    def append(self, b, U, m):
        """Take ``m`` slots at the end of block ``U`` in buffer ``b``; the first one's position."""
        return ti.atomic_add(self.n[U[0], U[1], b], m)

    @ti.func
    def mark(self, I, keep, D):
        """Slot ``I`` survives the next compaction into the block of cell ``D`` (member first), a
        neighbour of its own block (a step moves at most one cell per axis) or itself."""
        code = 0
        if keep:
            code = self.block_grid.direction(I[1], D) + 1
        self.keep[I] = ti.u8(code)

    @ti.func
    def marked(self, I):
        """Whether slot ``I`` survives the next compaction."""
        return self.keep[I] != 0

    @ti.func
    def unmark(self, I):
        """Slot ``I`` does not survive the next compaction."""
        self.keep[I] = ti.u8(0)

    @ti.kernel
    def truncate(self, b: ti.i32):
        """Drop what was appended to buffer ``b`` since the last compaction."""
        self.assume_active()
        for u in range(self.listed[None]):
            e, U, _, _ = self.unit(b, u)
            self.n[e, U[1], b] = self.fixed[e, U[1]]

    @ti.kernel
    def settle(self, b: ti.i32):
        """Keep what was appended to buffer ``b`` since the last compaction, where it lies (each new
        particle was appended to the block of its cell): what :meth:`compacted` gives when every
        slot is marked, without the moves."""
        self.assume_active()
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            self.kept[e] = 0
        for u in range(self.listed[None]):
            e, U, _, _ = self.unit(b, u)
            self.fixed[e, U[1]] = self.n[e, U[1], b]
            self.kept[e] += self.n[e, U[1], b]
