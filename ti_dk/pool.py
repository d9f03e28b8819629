"""Particle storage shared by the particle method and the hybrid: slots per member, growth,
one order-keeping compaction and one capacity rule.

Two layouts (scene key ``pool_layout``; the hybrid takes either, the particle method the flat one):

- :class:`ParticlePool` (``flat``): one array of slots per member, sized for the member's whole
  region; memory follows the particles of the busiest member.
- :class:`BlockPool` (``pointer``): a ``ti.root.pointer`` over blocks of cells, each active block
  holding its slots in dense chunks; only the blocks of the region and its ghost ring are active,
  so memory follows the region's particles, not the grid or the busiest member. Particles move
  between blocks by per-block counts and an exclusive scan (no ``dynamic`` appends, which
  contend: ``benchmarks/bench_pool.py``). Slower per step on 2 CPU cores, smaller in memory
  (``benchmarks/RESULTS.md``).

The hybrid reaches a particle through the same ti.funcs in both: a loop over :meth:`units`
(a member's chunk of slots, or a block), :meth:`unit` (its member, key and slot range),
:meth:`index` (the index of a slot in ``x``, ``pid``), :meth:`unit_of` and :meth:`append` (room
for new particles of a cell), :meth:`mark` / :meth:`marked` / :meth:`unmark` (whether a slot
survives the next :meth:`compacted`). A particle's random numbers are keyed on its ``pid``, never
on its slot, so both layouts give the same bits; :meth:`occupied` returns the particles sorted
by identity, so checkpoints are the same too.
"""

import itertools
import math

import numpy as np
import taichi as ti

from .grid import cell_of, exclusive_scan, numpy_dtype

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
    one (8 µs a read); many are copied at once (``to_numpy``: 180 µs in ellipse2d, a kernel
    whose parallel task costs most of it, which was 2 % of that run's time)."""
    E = counts.shape[-1]
    if E <= 16:
        return sum(int(counts[(*row, e)]) for e in range(E))
    return int(counts.to_numpy()[row].sum(dtype=np.int64))


def make(layout: str, grid, ensemble: int, real):
    """An empty hybrid pool of ``layout`` (one of :data:`LAYOUTS`) for ``grid``."""
    if layout == "pointer":
        return BlockPool(grid, ensemble, 1, real)
    return ParticlePool(ensemble, 1, grid.dim, real)


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
        self.cell_ordered = False  # slots are not grouped by cell (the hybrid sorts them at regrids)
        self.blocks = -(-capacity // BLOCK)  # compaction blocks per member
        self.x = ti.Vector.field(dim, real, shape=(buffers, ensemble, capacity))  # positions [length]
        if ids:  # identity: two words keying the particle's random numbers (solver-defined)
            self.pid = ti.Vector.field(2, ti.u32, shape=(buffers, ensemble, capacity))
        self.n = ti.field(ti.i32, shape=(buffers, ensemble))  # occupied slots per buffer and member
        self.kept = ti.field(ti.i32, shape=ensemble)  # slots the last compaction kept, per member
        self.span = ti.field(ti.i32, shape=())  # blocks holding particles in the buffer a loop reads (units)
        if buffers == 2:
            self.keep = ti.field(ti.u8, shape=(ensemble, capacity))  # 1: the slot survives the compaction
            self.offset = ti.field(ti.i32, shape=(ensemble, self.blocks))  # first target slot of each block

    @property
    def nbytes(self) -> int:
        """Bytes of the pool's slot fields (positions, identities, marks)."""
        slot = self.dim * np.dtype(numpy_dtype(self.real)).itemsize + 8 * self.ids
        return self.ensemble * self.capacity * (self.buffers * slot + (self.buffers == 2))

    def grown(self, capacity: int) -> "ParticlePool":
        """This pool, or (when ``capacity`` exceeds its own) a new one holding the same particles,
        with a quarter more slots than asked and at least twice the old: every new pool recompiles
        the kernels that take it (2.2 s at step 10 of ellipse2d, whose first regrid asked for 7 %
        more than the initial fit), so a region that drifts between regrids should not grow it."""
        if capacity <= self.capacity:
            return self
        capacity = max(capacity + capacity // 4, 2 * self.capacity)
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
        """Buffer ``b`` on the host: positions and identities of slots ``[0, max n)`` (each
        member's sorted by :func:`canonical` when the pool has ids), and ``n``."""
        n = self.n.to_numpy()[b]
        top = max(1, int(n.max()))
        x = self.x.to_numpy()[b, :, :top]
        return canonical(x, self.pid.to_numpy()[b, :, :top], n) if self.ids else (x, None, n)

    # -- the hybrid's interface (see the module docstring) ----------------------------------
    def fitted(self, need: np.ndarray, cells: np.ndarray) -> "ParticlePool":
        """A pool with room for ``need`` (``(ensemble, *cells)``: slots each cell may ask for) in
        every member (``cells``: where particles may lie; every cell may, here)."""
        axes = tuple(range(1, need.ndim))
        return self.grown(capacity(float(need.sum(axis=axes).max()) if self.ensemble else 0.0))

    def retain(self, cells: np.ndarray) -> None:
        """Nothing to release: the slots of a member are not tied to cells."""

    def restored(self, x: np.ndarray, pid: np.ndarray, n: np.ndarray, cells: np.ndarray) -> "ParticlePool":
        """A pool holding ``x``, ``pid`` (``(ensemble, slots, …)``, member ``e`` in its first ``n[e]``
        slots) in buffer 0, as after a compaction."""
        new = self.grown(capacity(x.shape[1]))
        new.load(x[None], pid[None], np.stack([n, np.zeros_like(n)]))
        new.kept.from_numpy(n.astype(np.int32))
        return new

    def compacted(self, b: int) -> "ParticlePool":
        """:meth:`compact` buffer ``b`` into the other (a flat pool never needs more room)."""
        self.compact(b)
        return self

    @ti.func
    def assume_active(self):
        """Nothing to do: a flat pool has no sparse storage (see :meth:`BlockPool.assume_active`)."""

    @ti.func
    def units(self, b):
        """Units of the particle loop over buffer ``b``: the chunks of :data:`BLOCK` slots of every
        member up to the fullest member's last particle (:attr:`span` chunks per member).

        Taichi 1.7.4's CPU backend (its default ``make_cpu_multithreading_loop`` transform) cuts a
        parallel range into one contiguous block per thread of at least 512 iterations. So the
        range is set here, at run time, not over the capacity: the empty slots beyond the
        particles (a third or more of a hybrid's pool) went to the last thread while the first
        walked every particle (a loop over 1.1 M slots whose first half held the work: 277 ms on
        1 thread and on 2; 2× faster with the range ending at the work). And the units are small
        (:data:`BLOCK`): with 256 slots, ellipse2d's 70,000 particles made 274 units, one block,
        and its walk ran on one thread (2.25 ms on 1 thread, 2.10 on 2; with 32 slots 2.12 and
        1.35)."""
        self.span[None] = 0
        ti.loop_config(serialize=True)  # over members: a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            ti.atomic_max(self.span[None], ti.min((self.n[b, e] + BLOCK - 1) // BLOCK, self.blocks))
        return self.ensemble * self.span[None]

    @ti.func
    def unit(self, b, u):
        """Member, key and occupied slot range ``[lo, hi)`` of unit ``u`` of :meth:`units` in buffer ``b``."""
        span = self.span[None]
        e, k = u // span, u % span
        return e, ti.Vector([e, 0]), k * BLOCK, ti.min(k * BLOCK + BLOCK, self.n[b, e])

    @ti.func
    def unit_of(self, e, C):
        """The key of the unit that takes new particles of cell ``C`` of member ``e``."""
        return ti.Vector([e, 0])

    @ti.func
    def first_new(self, U):
        """The first slot of unit ``U`` appended since the last compaction (the ghosts of a step)."""
        return self.kept[U[0]]

    @ti.func
    def index(self, b, U, p):
        """The index in ``x`` and ``pid`` of slot ``p`` of unit ``U`` in buffer ``b``."""
        return ti.Vector([b, U[0], p])

    @ti.func
    def append(self, b, U, m):
        """Reserve ``m`` slots of unit ``U`` in buffer ``b``; returns the first (it may lie beyond
        ``capacity``: the caller then asks for a larger pool)."""
        return ti.atomic_add(self.n[b, U[0]], m)

    @ti.func
    def mark(self, I, keep, D):
        """Whether slot ``I`` survives the next compaction (``D``: the member-first cell it lies in)."""
        self.keep[I[1], I[2]] = ti.u8(keep)

    @ti.func
    def marked(self, I):
        return self.keep[I[1], I[2]] != 0

    @ti.func
    def unmark(self, I):
        self.keep[I[1], I[2]] = ti.u8(0)

    @ti.kernel
    def compact(self, b: ti.i32):
        """Copy the slots of buffer ``b`` marked in :attr:`keep` to the front of the other buffer,
        in order (per-block counts, an exclusive scan over blocks, a scatter); :attr:`kept` and
        the other buffer's ``n`` get the count."""
        nxt = 1 - b
        for u in range(self.units(b)):
            e, _, lo, hi = self.unit(b, u)
            c = 0
            for p in range(lo, hi):
                c += ti.cast(self.keep[e, p], ti.i32)
            self.offset[e, lo // BLOCK] = c
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            total = exclusive_scan(self.offset, e, self.span[None])
            self.n[nxt, e] = total
            self.kept[e] = total
        for u in range(self.ensemble * self.span[None]):  # the units of the first loop
            e, _, lo, hi = self.unit(b, u)
            j = self.offset[e, lo // BLOCK]
            for p in range(lo, hi):
                if self.keep[e, p]:
                    self.x[nxt, e, j] = self.x[b, e, p]
                    if ti.static(self.ids):
                        self.pid[nxt, e, j] = self.pid[b, e, p]
                    j += 1

    @ti.kernel
    def truncate(self, b: ti.i32):
        """Drop what was appended to buffer ``b`` since the last compaction."""
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            self.n[b, e] = self.kept[e]

    @ti.kernel
    def settle(self, b: ti.i32):
        """Keep what was appended to buffer ``b`` since the last compaction, where it lies: what
        :meth:`compacted` gives when every slot is marked, without the copy."""
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            self.kept[e] = self.n[b, e]


@ti.data_oriented
class BlockPool:
    """The ``pointer`` layout: a ``ti.root.pointer`` over (member, block of :data:`SIDE` cells per
    axis), each active block holding two buffers of ``capacity`` slots; block ``B`` of member ``e``
    has key ``(e, B)`` (``B``: C-order index of the block) and holds the particles of its cells.
    A buffer's slots are dense arrays of :data:`CHUNK` slots under a second pointer, allocated as
    they fill: a dense array of ``capacity`` slots per block made every active block as large
    as the fullest (sphere3d at 64³: 470 MB of slots for 1.2 M particles, against 84 MB).

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

    def compacted(self, b: int) -> "BlockPool":
        """The marked slots of buffer ``b`` moved, in order, to the front of their target blocks in
        the other buffer; a larger pool first when a block would overflow."""
        pool = self
        while True:
            pool._scan(b)
            need = int(pool.need[None])
            if need <= pool.capacity:
                break
            pool = pool.grown(need)
        pool._scatter(b)
        return pool

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

    # -- the hybrid's interface (see the module docstring) ----------------------------------
    @ti.func
    def assume_active(self):
        """Let the calling kernel reach a block's own fields without activating it (a write to a
        pointer SNode otherwise checks for an active cell first). Every block a kernel of the
        hybrid touches is active, made so by :meth:`fitted`; only :meth:`_touch` activates
        blocks. Chunks of slots are activated by the writes that fill them."""
        ti.no_activate(self.n, self.cnt, self.off, self.fixed)

    @ti.func
    def units(self, b):
        """Units of the particle loop (over either buffer): the active blocks."""
        return self.listed[None]

    @ti.func
    def unit(self, b, u):
        """Member, key and occupied slot range ``[lo, hi)`` of active block ``u`` in buffer ``b``."""
        key = self.list[u]
        e = key // self.NB
        U = ti.Vector([e, key % self.NB])
        return e, U, 0, self.n[U[0], U[1], b]

    @ti.func
    def unit_of(self, e, C):
        """The key of the block of cell ``C`` of member ``e`` (a reservoir cell: the boundary block)."""
        B = 0
        for a in ti.static(range(self.dim)):
            B = B * self.nb[a] + ti.min(ti.max(C[a], 0), self.cells[a] - 1) // self.side
        return ti.Vector([e, B])

    @ti.func
    def first_new(self, U):
        return self.fixed[U[0], U[1]]

    @ti.func
    def index(self, b, U, p):
        return ti.Vector([U[0], U[1], b, p])

    @ti.func
    def append(self, b, U, m):
        return ti.atomic_add(self.n[U[0], U[1], b], m)

    @ti.func
    def _coords(self, B):
        c = ti.Vector.zero(ti.i32, self.dim)
        for k in ti.static(range(self.dim)):
            a = ti.static(self.dim - 1 - k)
            c[a] = B % self.nb[a]
            B //= self.nb[a]
        return c

    @ti.func
    def _linear(self, c):
        B = 0
        for a in ti.static(range(self.dim)):
            B = B * self.nb[a] + c[a]
        return B

    @ti.func
    def mark(self, I, keep, D):
        """Slot ``I`` survives the next compaction into the block of cell ``D`` (member first), a
        neighbour of its own block (a step moves at most one cell per axis) or itself."""
        code = 0
        if keep:
            s = self._coords(I[1])
            k = 0
            for a in ti.static(range(self.dim)):
                d = D[a + 1] // self.side - s[a]
                if d > 1:  # across a periodic side
                    d -= self.nb[a]
                elif d < -1:
                    d += self.nb[a]
                k = k * 3 + d + 1
            code = k + 1
        self.keep[I] = ti.u8(code)

    @ti.func
    def marked(self, I):
        return self.keep[I] != 0

    @ti.func
    def unmark(self, I):
        self.keep[I] = ti.u8(0)

    # -- kernels --------------------------------------------------------------------------
    @ti.kernel
    def _touch(self, keys: ti.types.ndarray()):
        for i in range(keys.shape[0]):
            e, B = keys[i] // self.NB, keys[i] % self.NB
            for b in ti.static(range(2)):  # activates the block; a reused block starts empty
                self.n[e, B, b] = 0
            self.fixed[e, B] = 0

    @ti.kernel
    def _drop(self, keys: ti.types.ndarray()):
        for i in range(keys.shape[0]):
            ti.deactivate(self.blk, [keys[i] // self.NB, keys[i] % self.NB])

    @ti.kernel
    def _trim(self):
        """Release the chunks past the occupied slots of each active block's two buffers."""
        for u in range(self.listed[None]):
            e, U, _, _ = self.unit(0, u)
            for b in ti.static(range(2)):
                for c in range((self.n[e, U[1], b] + CHUNK - 1) // CHUNK, self.capacity // CHUNK):
                    # explicit casts: without them Taichi warns "Field index not int32" in 3D
                    ti.deactivate(self.chunks, [ti.i32(e), ti.i32(U[1]), b, ti.i32(c)])

    @ti.kernel
    def _active_chunks(self) -> ti.i32:
        c = 0
        for _ in ti.grouped(self.chunks):
            c += 1
        return c

    @ti.kernel
    def _scan(self, b: ti.i32):
        """Count the marked slots of buffer ``b`` per block and neighbour; at each target block an
        exclusive scan over its neighbours (in the fixed order of :attr:`dirs`) gives each source
        its first slot there. Sets ``n`` of the other buffer, ``fixed``, ``kept`` and ``need``."""
        self.assume_active()
        nxt = 1 - b
        for u in range(self.listed[None]):
            _, U, lo, hi = self.unit(b, u)
            c = ti.Vector.zero(ti.i32, self.ndirs)  # local counts: no atomics on the block's fields
            for p in range(lo, hi):
                code = ti.cast(self.keep[U[0], U[1], b, p], ti.i32)
                if code:
                    c[code - 1] += 1
            for k in ti.static(range(self.ndirs)):
                self.cnt[U[0], U[1], k] = c[k]
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            self.kept[e] = 0
        self.need[None] = 0
        for u in range(self.listed[None]):
            e, T, _, _ = self.unit(b, u)
            t = self._coords(T[1])
            total = 0
            for k in ti.static(range(self.ndirs)):
                s = t
                ok = True
                for a in ti.static(range(self.dim)):
                    s[a] -= self.dirs[k][a]
                    if s[a] < 0 or s[a] >= self.nb[a]:
                        if ti.static(self.periodic[a]):
                            s[a] = (s[a] + self.nb[a]) % self.nb[a]
                        else:
                            ok = False
                if ok:
                    S = self._linear(s)
                    c = self.cnt[e, S, k]  # 0 where the source is inactive (only read, never activated)
                    if c > 0:
                        self.off[e, S, k] = total
                        total += c
            self.n[e, T[1], nxt] = total
            self.fixed[e, T[1]] = total
            self.kept[e] += total
            ti.atomic_max(self.need[None], total)

    @ti.kernel
    def _scatter(self, b: ti.i32):
        """Copy the marked slots of buffer ``b`` to the slots :meth:`_scan` gave them."""
        self.assume_active()
        nxt = 1 - b
        for u in range(self.listed[None]):
            e, S, lo, hi = self.unit(b, u)
            s = self._coords(S[1])
            T = ti.Vector.zero(ti.i32, self.ndirs)  # each neighbour's key, and the next slot there
            j = ti.Vector.zero(ti.i32, self.ndirs)
            for k in ti.static(range(self.ndirs)):
                t = s
                for a in ti.static(range(self.dim)):
                    t[a] = (t[a] + self.dirs[k][a] + self.nb[a]) % self.nb[a]
                T[k] = self._linear(t)
                j[k] = self.off[e, S[1], k]
            for p in range(lo, hi):
                code = ti.cast(self.keep[e, S[1], b, p], ti.i32)
                if code:
                    k = code - 1
                    self.x[e, T[k], nxt, j[k]] = self.x[e, S[1], b, p]
                    self.pid[e, T[k], nxt, j[k]] = self.pid[e, S[1], b, p]
                    j[k] += 1

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

    @ti.kernel
    def _copy(self, old: ti.template()):
        for u in range(self.listed[None]):
            e, U, _, _ = self.unit(0, u)
            for b in ti.static(range(2)):
                m = old.n[e, U[1], b]
                self.n[e, U[1], b] = m
                for p in range(ti.min(m, old.capacity)):
                    self.x[e, U[1], b, p] = old.x[e, U[1], b, p]
                    self.pid[e, U[1], b, p] = old.pid[e, U[1], b, p]
                    self.keep[e, U[1], b, p] = old.keep[e, U[1], b, p]
            self.fixed[e, U[1]] = old.fixed[e, U[1]]
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            self.kept[e] = old.kept[e]

    @ti.kernel
    def _put(self, x: ti.types.ndarray(), pid: ti.types.ndarray(), n: ti.types.ndarray()):
        """Buffer 0 from the host, each particle in the block of its cell (as :meth:`restored`)."""
        for u in range(self.listed[None]):
            e, U, _, _ = self.unit(0, u)
            self.n[e, U[1], 0] = 0
        self.need[None] = 0
        for e, i in ti.ndrange(self.ensemble, x.shape[1]):
            if i < n[e]:
                y = ti.Vector([x[e, i, a] for a in ti.static(range(self.dim))])
                C = ti.Vector([cell_of(y[a], self.real(self.grid.dx[a]), self.cells[a]) for a in ti.static(range(self.dim))])
                U = self.unit_of(e, C)
                j = self.append(0, U, 1)
                ti.atomic_max(self.need[None], j + 1)
                if j < self.capacity:
                    self.x[e, U[1], 0, j] = y
                    self.pid[e, U[1], 0, j] = ti.math.uvec2(pid[e, i, 0], pid[e, i, 1])
        for u in range(self.listed[None]):
            e, U, _, _ = self.unit(0, u)
            self.fixed[e, U[1]] = self.n[e, U[1], 0]
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            self.kept[e] = n[e]

    @ti.kernel
    def _counts(self, b: ti.i32, out: ti.types.ndarray()):
        for u in range(self.listed[None]):
            _, _, _, hi = self.unit(b, u)
            out[u] = hi

    @ti.kernel
    def _gather(self, b: ti.i32, start: ti.types.ndarray(), x: ti.types.ndarray(), pid: ti.types.ndarray()):
        for u in range(self.listed[None]):
            e, U, lo, hi = self.unit(b, u)
            for p in range(lo, hi):
                for a in ti.static(range(self.dim)):
                    x[e, start[u] + p, a] = self.x[e, U[1], b, p][a]
                for w in ti.static(range(2)):
                    pid[e, start[u] + p, w] = self.pid[e, U[1], b, p][w]
