"""Moving particles between the blocks of a :class:`~.blocks.BlockPool` at a compaction
(:class:`BlockMoves`): per-block counts, an exclusive scan at each target block over its neighbours
in a fixed order, and a scatter (no atomics, no appends)."""

import taichi as ti


@ti.data_oriented
class BlockMoves:
    """The compaction of ``pool`` (its fields and :class:`~.block_grid.BlockGrid` are the pool's):
    :meth:`scan`, then, when every target block has room, :meth:`scatter`."""

    def __init__(self, pool):
        self.pool, self.block_grid = pool, pool.block_grid

    @ti.kernel
    def scan(self, b: ti.i32):
        """Count the marked slots of buffer ``b`` per block and neighbour; at each target block an
        exclusive scan over its neighbours (in the fixed order of ``BlockGrid.dirs``) gives each
        source its first slot there. Sets ``n`` of the other buffer, ``fixed``, ``kept`` and ``need``."""
        p, g = self.pool, self.block_grid
        p.assume_active()
        nxt = 1 - b
        for u in range(p.listed[None]):
            _, U, lo, hi = p.unit(b, u)
            c = ti.Vector.zero(ti.i32, g.ndirs)  # local counts: no atomics on the block's fields
            for q in range(lo, hi):
                code = ti.cast(p.keep[U[0], U[1], b, q], ti.i32)
                if code:
                    c[code - 1] += 1
            for k in ti.static(range(g.ndirs)):
                p.cnt[U[0], U[1], k] = c[k]
        ti.loop_config(serialize=True)  # a serial task (grid.exclusive_scan)
        for e in range(p.ensemble):
            p.kept[e] = 0
        p.need[None] = 0
        for u in range(p.listed[None]):
            e, T, _, _ = p.unit(b, u)
            t = g.coords(T[1])
            total = 0
            for k in ti.static(range(g.ndirs)):
                S, ok = g.source(t, k)
                if ok:
                    c = p.cnt[e, S, k]  # 0 where the source is inactive (only read, never activated)
                    if c > 0:
                        p.off[e, S, k] = total
                        total += c
            p.n[e, T[1], nxt] = total
            p.fixed[e, T[1]] = total
            p.kept[e] += total
            ti.atomic_max(p.need[None], total)

    @ti.kernel
    def scatter(self, b: ti.i32):
        """Copy the marked slots of buffer ``b`` to the slots :meth:`scan` gave them."""
        p, g = self.pool, self.block_grid
        p.assume_active()
        nxt = 1 - b
        for u in range(p.listed[None]):
            e, S, lo, hi = p.unit(b, u)
            s = g.coords(S[1])
            T = ti.Vector.zero(ti.i32, g.ndirs)  # each neighbour's key, and the next slot there
            j = ti.Vector.zero(ti.i32, g.ndirs)
            for k in ti.static(range(g.ndirs)):
                T[k] = g.target(s, k)
                j[k] = p.off[e, S[1], k]
            for q in range(lo, hi):
                code = ti.cast(p.keep[e, S[1], b, q], ti.i32)
                if code:
                    k = code - 1
                    p.x[e, T[k], nxt, j[k]] = p.x[e, S[1], b, q]
                    p.pid[e, T[k], nxt, j[k]] = p.pid[e, S[1], b, q]
                    j[k] += 1
