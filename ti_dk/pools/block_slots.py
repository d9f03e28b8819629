"""How the hybrid's kernels reach the slots of a :class:`~.blocks.BlockPool` (the same ti.funcs as the
flat pool's, see :mod:`ti_dk.pools`) and the kernels that activate and release its blocks and chunks."""

import taichi as ti

from .slots import CHUNK


@ti.data_oriented
class BlockSlots:
    """Slot access and block activation of :class:`~.blocks.BlockPool` (its fields are made there)."""

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
    def split_unit(self, b, u):
        """:meth:`unit` with its slots cut at ``mid``: ``(e, U, lo, mid, hi)``, ``[lo, mid)`` held since
        the last compaction, ``[mid, hi)`` appended since (:meth:`new_unit`)."""
        e, U, lo, hi = self.unit(b, u)
        return e, U, lo, self.fixed[U[0], U[1]], hi

    @ti.func
    def unit_of(self, e, C):
        """The key of the block of cell ``C`` of member ``e`` (a reservoir cell: the boundary block)."""
        B = 0
        for a in ti.static(range(self.dim)):
            B = B * self.nb[a] + ti.min(ti.max(C[a], 0), self.cells[a] - 1) // self.side
        return ti.Vector([e, B])

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
        """Whether slot ``I`` survives the next compaction."""
        return self.keep[I] != 0

    @ti.func
    def unmark(self, I):
        """Slot ``I`` does not survive the next compaction."""
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
