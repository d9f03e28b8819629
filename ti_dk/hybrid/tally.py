"""What moving the hybrid's region costs, summed on the device (paper §3.2): the particle slots the
pool must offer around a regrid and the SPDE content the newly covered cells hold, so that a regrid
reads back two numbers instead of the grid's density."""

import numpy as np
import taichi as ti

from ..core.grid import column_hit, row_cell, row_count
from ..methods.records import small


@ti.data_oriented
class Tally:
    """The region a regrid moves to (:attr:`target`) and the two sums of the move.

    A cell near the move (covered now, or within Chebyshev distance 1 of the target, across periodic
    sides: where particles can be while the region moves) may ask for ``⌈max(q V_c, 0)⌉`` slots (its
    content, whole: the region and its ghost ring full), and a target cell beside a Dirichlet side
    for ``reservoir_ppc_max · 3^(d−1)`` more (its reservoir ghosts). The sums run row by row, each
    row in order and the rows in order, so that they are the same bits on any thread count.
    """

    def __init__(self, region):
        self.region, self.grid = region, region.grid
        E, n = region.ensemble, region.n
        self.target = ti.field(ti.u8, shape=(E, *n))  # 1 where the cell is in the region a regrid moves to
        # per row (core.grid.row_count): slots asked, content covered anew [particles], cells the move uncovers, cells it covers anew
        self.rows = ti.field(ti.f64, shape=(E, row_count(n), 4))
        # all members: the most slots a member asks, the content covered anew [particles], cells uncovered, members whose region moves
        self.out = ti.field(ti.f64, shape=4)

    def aim(self, masks: np.ndarray) -> None:
        """Make ``masks`` (``(ensemble, *cells)`` booleans) the target (a region made on the host)."""
        self.target.from_numpy(np.ascontiguousarray(masks, dtype=np.uint8))

    def count(self, spde) -> tuple[float, float, int, int]:
        """The most slots any member may ask for around the move to :attr:`target`, the SPDE content
        ``Σ q V_c`` of the cells the move covers anew, how many cells it uncovers, and how many
        members' regions it changes, all members (32 bytes read back)."""
        self._sum(spde)
        most, removed, gone, members = small(self.out)
        return float(most), float(removed), int(gone), int(members)

    def per_cell(self, spde) -> np.ndarray:
        """The slots each cell may ask for, ``(ensemble, *cells)`` (a pool that plans by cell)."""
        out = np.zeros(self.target.shape, dtype=np.float64)
        self._fill(spde, out)
        return out

    @ti.func
    def _near(self, e, C, before, here, after) -> bool:
        """Whether cell ``C`` of member ``e`` is covered now or within distance 1 of the target, given
        :meth:`_column` at the last axis's ``k − 1``, ``k`` and ``k + 1``."""
        return before or here or after or self.region.covered[self.region.member(e, C)] != 0

    @ti.func
    def _column(self, e, C, k) -> bool:
        """Whether a target cell lies within distance 1 of ``C`` along every axis but the last, at
        position ``k`` of the last axis (:func:`~ti_dk.core.grid.column_hit`)."""
        return column_hit(self.grid, self.target, e, C, k)

    @ti.func
    def _cell(self, spde: ti.template(), e, C, near):
        """Cell ``C`` of member ``e`` (``near``: :meth:`_near`'s answer): the slots it may ask for, and its
        content if the move covers it anew."""
        r = self.region
        J = r.member(e, C)
        content = ti.cast(spde.q[J], ti.f64) * ti.static(self.grid.cell_volume)
        need, gained = 0.0, 0.0
        if near:
            need = ti.ceil(ti.max(content, 0.0))
        if self.target[J] != 0:
            need += ti.static(self.grid.reservoir_ppc_max * 3 ** (self.grid.dim - 1) if self.grid.has_dirichlet else 0.0)
            if r.covered[J] == 0:
                gained = content
        return need, gained, ti.cast(self.target[J] == 0 and r.covered[J] != 0, ti.f64), \
            ti.cast(self.target[J] != 0 and r.covered[J] == 0, ti.f64)

    @ti.kernel
    def _sum(self, spde: ti.template()):
        """:attr:`rows`, then :attr:`out` from them, in a fixed order."""
        n, d, rows = ti.static(self.region.n, self.grid.dim, self.rows.shape[1])
        for e, i in ti.ndrange(self.target.shape[0], rows):  # rows in parallel; each row's cells in order
            need, gained, gone, new = 0.0, 0.0, 0.0, 0.0
            before, here = False, False  # _column at the last axis's k − 1 and k (k + 1 made at k)
            for R in ti.grouped(ti.ndrange(*(n[1:] if d > 1 else n))):
                C = ti.Vector.zero(ti.i32, d)
                if ti.static(d > 1):
                    C = row_cell(i, R, d)
                else:
                    C = R
                k = C[d - 1]
                if k == 0:
                    before, here = self._column(e, C, -1), self._column(e, C, 0)
                after = self._column(e, C, k + 1)
                a, b, g, w = self._cell(spde, e, C, self._near(e, C, before, here, after))
                need += a
                gained += b
                gone += g
                new += w
                before, here = here, after
            self.rows[e, i, 0] = need
            self.rows[e, i, 1] = gained
            self.rows[e, i, 2] = gone
            self.rows[e, i, 3] = new
        ti.loop_config(serialize=True)
        for _ in range(1):
            most, removed, gone, members = 0.0, 0.0, 0.0, 0.0
            for e in range(self.target.shape[0]):
                total, changed = 0.0, 0.0
                for i in range(rows):
                    total += self.rows[e, i, 0]
                    removed += self.rows[e, i, 1]
                    gone += self.rows[e, i, 2]
                    changed += self.rows[e, i, 2] + self.rows[e, i, 3]
                most = ti.max(most, total)
                members += ti.cast(changed > 0, ti.f64)
            self.out[0] = most
            self.out[1] = removed
            self.out[2] = gone
            self.out[3] = members

    @ti.kernel
    def _fill(self, spde: ti.template(), out: ti.types.ndarray()):
        """Each cell's slots into ``out`` (:meth:`per_cell`)."""
        for J in ti.grouped(self.target):
            C = ti.Vector([J[a + 1] for a in ti.static(range(self.grid.dim))])
            k = C[self.grid.dim - 1]
            near = self._near(J[0], C, self._column(J[0], C, k - 1), self._column(J[0], C, k),
                              self._column(J[0], C, k + 1))
            need, _gained, _gone, _new = self._cell(spde, J[0], C, near)
            out[J] = need
