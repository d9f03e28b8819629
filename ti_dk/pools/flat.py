"""The ``flat`` layout: one array of slots per member (:class:`ParticlePool`)."""

import numpy as np
import taichi as ti

from ..core.grid import exclusive_scan, numpy_dtype
from .slots import BLOCK, canonical, capacity


@ti.data_oriented
class ParticlePool:
    """The particles of every member: buffer ``b`` of member ``e`` holds slots ``[0, n[b, e])``.

    With ``ids`` every particle carries its identity (two words that key its random numbers;
    otherwise the slot is the identity, and particles neither enter nor leave): then a step marks
    the slots to ``keep`` and :meth:`compact` closes the gaps in place. A second buffer
    (``buffers = 2``) takes the cell-order sort of the hybrid's regrids (:meth:`Coupling.sort`). A
    member that needs more than ``capacity`` slots gets a larger pool from :meth:`grown`.
    """

    def __init__(self, ensemble: int, capacity: int, dim: int, real, buffers: int = 2, ids: bool = True,
                 light: bool = False):
        self.ensemble, self.capacity, self.dim, self.real = ensemble, capacity, dim, real
        self.buffers, self.ids = buffers, ids
        self.light = light  # the compaction's loops are short: serial tasks (the hybrid's pool: core.grid.light)
        self.cell_ordered = False  # slots are not grouped by cell (the hybrid sorts them at regrids)
        self.by_cell = False  # plans its room per member: grown(capacity(the most any member needs)) is fitted()
        self.in_place = True  # compacts in place (compact_here), never growing: a kernel that marks may compact too
        self.blocks = -(-capacity // BLOCK)  # compaction blocks per member
        self.x = ti.Vector.field(dim, real, shape=(buffers, ensemble, capacity))  # positions [length]
        if ids:  # identity: two words keying the particle's random numbers (solver-defined)
            self.pid = ti.Vector.field(2, ti.u32, shape=(buffers, ensemble, capacity))
        self.n = ti.field(ti.i32, shape=(buffers, ensemble))  # occupied slots per buffer and member
        self.kept = ti.field(ti.i32, shape=ensemble)  # slots the last compaction kept, per member
        self.span = ti.field(ti.i32, shape=())  # blocks holding particles in the buffer a loop reads (units)
        self.fresh = ti.field(ti.i32, shape=())  # most chunks a member appended since the last compaction (new_units)
        if ids:  # particles enter and leave: the compaction's fields
            self.keep = ti.field(ti.u8, shape=(ensemble, capacity))  # 1: the slot survives the compaction
            self.offset = ti.field(ti.i32, shape=(ensemble, self.blocks))  # marked slots before each block
            self.tail = ti.field(ti.i32, shape=(ensemble, capacity))  # the marked slots past the kept count, by rank

    @property
    def nbytes(self) -> int:
        """Bytes of the pool's slot fields (positions, identities, marks)."""
        slot = self.dim * np.dtype(numpy_dtype(self.real)).itemsize + 8 * self.ids
        return self.ensemble * self.capacity * (self.buffers * slot + 5 * self.ids)  # keep, tail

    def grown(self, capacity: int, planned: int = 0) -> "ParticlePool":
        """This pool, or (when ``capacity`` exceeds its own) a new one holding the same particles,
        with a quarter more slots than asked, at least twice the old and at least ``planned``
        (the hybrid's first region makes its pool so: :func:`~ti_dk.scene.estimates.hybrid_slots`):
        every new pool recompiles the kernels that take it (seconds), so a region that drifts
        between regrids should not grow it each time."""
        if capacity <= self.capacity:
            return self
        capacity = max(capacity + capacity // 4, 2 * self.capacity, planned)
        new = ParticlePool(self.ensemble, capacity, self.dim, self.real, self.buffers, self.ids, self.light)
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
    def retain(self, cells: np.ndarray) -> None:
        """Nothing to release: the slots of a member are not tied to cells."""

    def restored(self, x: np.ndarray, pid: np.ndarray, n: np.ndarray, cells: np.ndarray) -> "ParticlePool":
        """A pool holding ``x``, ``pid`` (``(ensemble, slots, …)``, member ``e`` in its first ``n[e]``
        slots) in buffer 0, as after a compaction."""
        new = self.grown(capacity(x.shape[1]))
        new.load(x[None], pid[None], np.stack([n, np.zeros_like(n)]))
        new.kept.from_numpy(n.astype(np.int32))
        return new

    def compacted(self, b: int) -> tuple["ParticlePool", int]:
        """:meth:`compact` buffer ``b``; returns the pool (a flat pool never needs more room) and
        the buffer that holds the particles (``b``: in place)."""
        self.compact(b)
        return self, b

    @ti.func
    def assume_active(self):
        """Nothing to do: a flat pool has no sparse storage (see :meth:`BlockPool.assume_active`)."""

    @ti.func
    def units(self, b):
        """Units of the particle loop over buffer ``b``: the chunks of :data:`BLOCK` slots of every
        member up to the fullest member's last particle (:attr:`span` chunks per member).

        Taichi 1.7.4's CPU backend (its default ``make_cpu_multithreading_loop`` transform) cuts a
        parallel range into one contiguous block per thread of at least 512 iterations. So the
        range is set here, at run time, not over the capacity: otherwise the empty slots beyond
        the particles (a third or more of a hybrid's pool) go to the last thread while the first
        walks every particle. And the units are small (:data:`BLOCK`), so that a loop has enough
        of them to give both threads work."""
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
    def split_unit(self, b, u):
        """:meth:`unit` with its slots cut at ``mid``: ``(e, U, lo, mid, hi)``, ``[lo, mid)`` held since
        the last compaction, ``[mid, hi)`` appended since (:meth:`new_unit`)."""
        e, U, lo, hi = self.unit(b, u)
        return e, U, lo, ti.min(ti.max(self.kept[e], lo), hi), hi

    @ti.func
    def unit_of(self, e, C):
        """The key of the unit that takes new particles of cell ``C`` of member ``e``."""
        return ti.Vector([e, 0])

    @ti.func
    def new_units(self, b):
        """Units of a loop over the slots appended to buffer ``b`` since the last compaction (the
        ghosts of a step): chunks of :data:`BLOCK` slots from each member's ``kept``, :attr:`fresh`
        of them per member. Not :meth:`units` with the old slots skipped: that loop would visit
        every chunk of the pool at every step."""
        self.fresh[None] = 0
        ti.loop_config(serialize=True)  # over members: a serial task (grid.exclusive_scan)
        for e in range(self.ensemble):
            ti.atomic_max(self.fresh[None], (self.n[b, e] - self.kept[e] + BLOCK - 1) // BLOCK)
        return self.ensemble * self.fresh[None]

    @ti.func
    def new_unit(self, b, u):
        """Member, key and slot range ``[lo, hi)`` of unit ``u`` of :meth:`new_units` in buffer ``b``."""
        fresh = self.fresh[None]
        e, k = u // fresh, u % fresh
        lo = self.kept[e] + k * BLOCK
        return e, ti.Vector([e, 0]), lo, ti.min(lo + BLOCK, self.n[b, e])

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
        """Whether slot ``I`` survives the next compaction."""
        return self.keep[I[1], I[2]] != 0

    @ti.func
    def unmark(self, I):
        """Slot ``I`` does not survive the next compaction."""
        self.keep[I[1], I[2]] = ti.u8(0)

    @ti.kernel
    def compact(self, b: ti.i32):
        """:meth:`compact_here` in a launch of its own."""
        self.compact_here(b)

    @ti.func
    def compact_here(self, b):
        """Keep the slots of buffer ``b`` marked in :attr:`keep`, in place: with K of them marked,
        the marked slots below K stay where they are and the i-th unmarked slot below K (a hole,
        in slot order) takes the i-th marked slot at or past K; :attr:`kept` and ``n`` get K.
        Ranks come from per-block counts and an exclusive scan over blocks, so the result is the
        same on any thread count. A particle's random numbers are keyed on its identity, never
        on its slot, so the order changes no result; a step then moves the particles that left
        or entered the region, not all of them (a copy of every particle to the other buffer
        cost the 3D hybrid 8 % of its step). Called at a kernel's top level (its loops are then
        tasks of their own): the hybrid compacts in its particle step's launch (:attr:`in_place`)."""
        units = self.units(b)  # (a serial loop: a loop_config before it would be its, not the next's)
        ti.loop_config(serialize=ti.static(self.light))
        for u in range(units):
            e, _, lo, hi = self.unit(b, u)
            c = 0
            for p in range(lo, hi):
                c += ti.cast(self.keep[e, p], ti.i32)
            self.offset[e, lo // BLOCK] = c
        # a serial task (grid.exclusive_scan): the scan, then the tails by rank, the marked slots at or
        # past k (a few blocks: a parallel loop would cost a start of the thread pool, more than them)
        ti.loop_config(serialize=True)
        for e in range(self.ensemble):
            k = exclusive_scan(self.offset, e, self.span[None])
            r = 0
            for p in range(k, self.n[b, e]):
                if self.keep[e, p]:
                    self.tail[e, r] = p
                    r += 1
            self.kept[e] = k
            self.n[b, e] = k  # unit() now ends each member's last block at k
        ti.loop_config(serialize=ti.static(self.light))
        for u in range(self.ensemble * self.span[None]):  # each hole below k takes the tail of its rank
            e, _, lo, hi = self.unit(b, u)
            k = self.kept[e]
            marked = k - self.offset[e, lo // BLOCK]  # from lo on; in this block alone:
            if lo // BLOCK + 1 < self.span[None]:
                marked = self.offset[e, lo // BLOCK + 1] - self.offset[e, lo // BLOCK]
            # a block below k with a hole (most have none), or the one that k cuts
            if lo < k and (marked < BLOCK or lo + BLOCK > k):
                r = lo - self.offset[e, lo // BLOCK]  # holes before lo
                for p in range(lo, ti.min(hi, k)):
                    if not self.keep[e, p]:
                        t = self.tail[e, r]
                        self.x[b, e, p] = self.x[b, e, t]
                        self.pid[b, e, p] = self.pid[b, e, t]  # (a pool compacts only with ids)
                        r += 1

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
