"""Moving particles between the blocks of a :class:`~.blocks.BlockPool`: per-block counts, an exclusive
scan at each target block over its neighbours in a fixed order, and a scatter (no atomics, no
appends); and the copies in and out of the pool."""

import taichi as ti

from ..core.grid import cell_of


@ti.data_oriented
class BlockMoves:
    """Compaction and copies of :class:`~.blocks.BlockPool` (its fields are made there)."""

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
