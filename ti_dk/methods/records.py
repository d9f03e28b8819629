"""What a run reads back, made small on the device: a per-member record (each member's particles,
negative cells, the particles and cells of its particle region, and the particles in each named set
of cells: ``ensemble × (4 + sets)`` numbers instead of the whole density), and a solver's scalar
diagnostics in one read."""

import numpy as np
import taichi as ti

from ..core.grid import Grid, on_cpu, prefixed, row_cell, row_count

RECORD = ("mass", "negative_cells", "particles", "region_cells")  # the fixed columns, then one per set


@ti.data_oriented
class MemberSums:
    """Per-member sums over a solver's content field (:meth:`Solver.content`).

    Row by row (a row: a member and a first index; in 1D a member), each row's cells in order, then
    each member's rows in order, so that the sums are the same bits on any thread count.
    """

    def __init__(self, grid: Grid, ensemble: int, sets: dict[str, np.ndarray]):
        self.grid, self.ensemble, self.names = grid, ensemble, tuple(sets)
        self.n_sets = len(sets)
        n, k = grid.cells, len(RECORD) + len(sets)
        self.sets = ti.field(ti.u8, shape=(max(len(sets), 1), *n))  # 1 where the cell is in set s (by name)
        if sets:
            self.sets.from_numpy(np.stack(list(sets.values())).astype(np.uint8))
        self.rows = ti.field(ti.f64, shape=(ensemble, row_count(n), k))  # per row (core.grid.row_count): its part of each column
        self.out = ti.field(ti.f64, shape=(ensemble, k))  # per member: each column [particles or cells]

    def record(self, field, scale: float, region=None) -> dict[str, np.ndarray]:
        """Each member's columns of :data:`RECORD` (``particles`` and ``region_cells`` only with a
        ``region``, a ``(ensemble, *cells)`` u8 field) and one per set, by its name: the content is
        ``field · scale`` [particles per cell]. One read of ``ensemble × (4 + sets)`` numbers."""
        if region is None:
            self._sum(field, scale, self.sets, False)
        else:
            self._sum(field, scale, region, True)
        out = self.out.to_numpy()
        rec = {name: out[:, i] for i, name in enumerate(RECORD)}
        rec["negative_cells"] = rec["negative_cells"].astype(np.int64)
        if region is None:
            del rec["particles"], rec["region_cells"]
        else:
            rec["region_cells"] = rec["region_cells"].astype(np.int64)
        return rec | {name: out[:, len(RECORD) + s] for s, name in enumerate(self.names)}

    @ti.func
    def _add(self, field: ti.template(), scale: ti.f64, region: ti.template(), has_region: ti.template(),
             e, i, C):
        """Cell ``C`` of member ``e`` added to row ``(e, i)``."""
        J = prefixed(e, C, self.grid.dim)
        v = ti.cast(field[J], ti.f64) * scale
        self.rows[e, i, 0] += v
        if v < 0:
            self.rows[e, i, 1] += 1.0
        if ti.static(has_region):
            if region[J] != 0:
                self.rows[e, i, 2] += v
                self.rows[e, i, 3] += 1.0
        for s in ti.static(range(self.n_sets)):
            if self.sets[prefixed(s, C, self.grid.dim)] != 0:
                self.rows[e, i, ti.static(len(RECORD) + s)] += v

    @ti.kernel
    def _sum(self, field: ti.template(), scale: ti.f64, region: ti.template(), has_region: ti.template()):
        n, d, rows, k = ti.static(self.grid.cells, self.grid.dim, self.rows.shape[1], self.rows.shape[2])
        for e, i in ti.ndrange(self.ensemble, rows):
            for c in ti.static(range(k)):
                self.rows[e, i, c] = 0.0
            if ti.static(d == 1):
                for j in range(n[0]):
                    self._add(field, scale, region, has_region, e, i, ti.Vector([j]))
            else:
                for R in ti.grouped(ti.ndrange(*n[1:])):
                    self._add(field, scale, region, has_region, e, i, row_cell(i, R, d))
        for e in range(self.ensemble):
            for c in ti.static(range(k)):
                total = 0.0
                for i in range(rows):
                    total += self.rows[e, i, c]
                self.out[e, c] = total


def small(field) -> np.ndarray:
    """The values of a small 1-d field on the host: on the CPU one element at a time (a few µs
    each, where ``to_numpy`` launches a parallel copy: about 90 µs on 2 cores), elsewhere by one
    ``to_numpy`` (one sync, where every element read would be one)."""
    if on_cpu():
        return np.array([field[i] for i in range(field.shape[0])])
    return field.to_numpy()


@ti.data_oriented
class Scalars:
    """0-d fields read back together: on a GPU one kernel copies them (as f64: exact for the counts,
    below 2^53) into one small array, read once, instead of one sync and one launch per field; on
    the CPU, where that costs more than the reads it saves, each is read (:func:`small`)."""

    def __init__(self, fields: list):
        self.fields, self.count = fields, len(fields)
        self.out = ti.field(ti.f64, shape=self.count)  # the fields' values, in order

    def read(self) -> np.ndarray:
        """The fields' values now, in order (float64)."""
        if on_cpu():
            return np.array([f[None] for f in self.fields], dtype=np.float64)
        self._pack()
        return self.out.to_numpy()

    @ti.kernel
    def _pack(self):
        for i in ti.static(range(self.count)):
            self.out[i] = ti.cast(self.fields[i][None], ti.f64)
