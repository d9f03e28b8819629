"""The flat lists of the hybrid's ghost ring and covered cells (paper §3.2), made on the device from
the covered mask, so that a regrid reads back their two lengths and nothing grid-sized."""

import math

import taichi as ti

from ..core.grid import DIRICHLET, SCAN_BLOCK, block_scan, column_hit, prefixed
from ..methods.records import small


@ti.data_oriented
class CellLists:
    """Makes :class:`~.region.Region`'s ``ring_list``, ``cover_list`` and ``near_list`` from its ``covered``.

    Both lists hold flat (C-order, member-first) indices, ascending, the order of
    ``np.flatnonzero``, so a loop over them visits cells in a fixed order whatever the thread count:
    each row along the last axis counts its cells, the counts of every row of every member are
    scanned by blocks (:func:`~ti_dk.core.grid.block_scan`), and each row writes its cells from its
    offset. A cell of the padded grid (one ghost layer a side) is a ghost cell where it is not
    covered and a covered cell lies within Chebyshev distance 1 of it (across periodic sides); beyond
    the grid only beyond a Dirichlet side (a reservoir cell), and never beyond two sides at once.
    """

    def __init__(self, region):
        self.region, self.grid, self.dim = region, region.grid, region.dim
        E, n, padded = region.ensemble, region.n, region.padded
        self.ring = ti.field(ti.u8, shape=(E, *padded))  # 1 where the padded cell is a ghost cell
        # per row along the last axis (member first): its ghost cells, then where the first lies in the list
        self.ring_rows = ti.field(ti.i32, shape=E * math.prod(padded[:-1]))
        self.cover_rows = ti.field(ti.i32, shape=E * math.prod(n[:-1]))  # likewise, covered cells
        self.sums = ti.field(ti.i32, shape=-(-self.ring_rows.shape[0] // SCAN_BLOCK))  # block_scan's scratch
        self.sizes = ti.field(ti.i32, shape=2)  # entries of ring_list and cover_list

    def make(self) -> tuple[int, int]:
        """The lists from ``covered`` as it is; returns their lengths (8 bytes read back)."""
        self._make()
        n_ring, n_cover = small(self.sizes)
        return int(n_ring), int(n_cover)

    @ti.func
    def _ghost(self, e, C, before, here, after) -> bool:
        """Whether padded cell ``C`` (cell coordinates, −1 … n) of member ``e`` is a ghost cell, given
        :func:`column_hit` of ``covered`` at the last axis's ``C − 1``, ``C``, ``C + 1``."""
        r = self.region
        outside, allowed = 0, True
        for a in ti.static(range(self.dim)):
            if C[a] < 0:
                outside += 1
                allowed = allowed and ti.static(self.grid.boundary[a][0] == DIRICHLET)
            elif C[a] >= r.n[a]:
                outside += 1
                allowed = allowed and ti.static(self.grid.boundary[a][1] == DIRICHLET)
        ghost = False
        if outside == 0:
            ghost = r.covered[prefixed(e, C, self.dim)] == 0
        elif outside == 1:
            ghost = allowed
        return ghost and (before or here or after)

    @ti.func
    def _row(self, R, shape: ti.template()):
        """Member ``R[0]``'s row ``R[1:]`` (a row of a grid of ``shape``, less its last axis) as an index of the row fields."""
        i = R[0]
        for a in ti.static(range(self.dim - 1)):
            i = i * shape[a] + R[a + 1]
        return i

    @ti.kernel
    def _make(self):
        r = self.region
        d, n, P = ti.static(self.dim, r.n, r.padded)
        covered = ti.static(r.covered)
        for R in ti.grouped(ti.ndrange(r.ensemble, *P[:-1])):  # ghost cells per row (marked in `ring`)
            C = ti.Vector([R[a + 1] - 1 for a in ti.static(range(d - 1))] + [-1])
            before, here = column_hit(self.grid, covered, R[0], C, -2), column_hit(self.grid, covered, R[0], C, -1)
            c = 0
            for j in range(P[d - 1]):
                C[d - 1] = j - 1
                after = column_hit(self.grid, covered, R[0], C, j)
                g = self._ghost(R[0], C, before, here, after)
                self.ring[prefixed(R[0], C + 1, d)] = ti.u8(g)
                c += ti.cast(g, ti.i32)
                before, here = here, after
            self.ring_rows[self._row(R, P)] = c
        for R in ti.grouped(ti.ndrange(r.ensemble, *n[:-1])):  # covered cells per row
            c = 0
            for j in range(n[d - 1]):
                c += ti.cast(covered[ti.Vector([R[a] for a in ti.static(range(d))] + [j])] != 0, ti.i32)
            self.cover_rows[self._row(R, n)] = c
        block_scan(self.ring_rows, self.sums, self.sizes, 0)
        block_scan(self.cover_rows, self.sums, self.sizes, 1)
        for R in ti.grouped(ti.ndrange(r.ensemble, *P[:-1])):  # each row's ghost cells from its offset, with their covered neighbours
            i = self.ring_rows[self._row(R, P)]
            base = self._row(R, P) * P[d - 1]  # the flat index of the row's first cell
            for j in range(P[d - 1]):
                Q = ti.Vector([R[a] for a in ti.static(range(d))] + [j])
                if self.ring[Q]:
                    r.ring_list[i] = base + j
                    C = ti.Vector([Q[a + 1] - 1 for a in ti.static(range(d))])
                    r.near_list[i] = r.near(R[0], C)
                    i += 1
        for R in ti.grouped(ti.ndrange(r.ensemble, *n[:-1])):  # each row's covered cells from its offset
            i = self.cover_rows[self._row(R, n)]
            base = self._row(R, n) * n[d - 1]
            for j in range(n[d - 1]):
                if covered[ti.Vector([R[a] for a in ti.static(range(d))] + [j])] != 0:
                    r.cover_list[i] = base + j
                    i += 1
