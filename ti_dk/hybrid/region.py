"""The hybrid's particle region (paper §3.2): on the device the covered mask, the tile flags and the
flat lists of ring and covered cells (:mod:`.lists`); on the host each member's boxes and, when
asked, a copy of the mask.

The region comes from tiles flagged on the device (:mod:`.tiles`) or from Berger–Rigoutsos boxes
(:mod:`.clustering`, host NumPy); everything downstream reads the cell mask, so nothing depends on how
the region was cut into boxes.
"""

import math

import numpy as np
import taichi as ti

from . import clustering, tiles
from ..core.grid import PERIODIC, Grid, offset, prefixed, wrap
from .lists import CellLists


@ti.data_oriented
class Region:
    """The particle region of every member: a cell mask, its ghost ring and their cell lists.

    The ghost ring holds the cells outside the region within Chebyshev distance 1 of it (across
    periodic sides) and the Dirichlet reservoir cells beyond covered boundary cells; it lives on
    the padded grid (one ghost layer per side, padded index = cell index + 1). The lists hold
    flat (C-order) indices, ascending, so a loop over them visits cells in a fixed order.
    """

    def __init__(self, grid: Grid, ensemble: int, params: clustering.RegridParams):
        self.grid, self.ensemble, self.params = grid, ensemble, params
        self.dim, self.n = grid.dim, grid.cells
        self.padded = tuple(m + 2 for m in self.n)  # the grid plus one layer of ghost cells per side
        self.periodic = tuple(lo == PERIODIC for lo, _ in grid.boundary)
        E, n = ensemble, self.n
        self.covered = ti.field(ti.u8, shape=(E, *n))  # 1 where the cell is in the particle region
        self.ring_list = ti.field(ti.i32, shape=E * math.prod(self.padded))  # flat indices of ghost cells
        self.cover_list = ti.field(ti.i32, shape=E * math.prod(n))  # flat indices of covered cells
        self.near_list = ti.field(ti.u32, shape=self.ring_list.shape)  # each ring cell's covered neighbours (near)
        self.low = ti.field(ti.i32, shape=())  # uncovered cells below the extension's trigger at the last count_low
        self.n_ring, self.n_cover = 0, 0  # lengths of the two lists
        self.tile = tiles.side_for(params.tile, self.n, params.region_from)  # the tiles' side in cells
        self.tiles = tiles.Tiles(grid, E, self.tile, params.buffer) if params.region == "tiles" else None
        self._boxes: list[list[clustering.Box]] = [[] for _ in range(E)]  # boxes: each member's region
        self._box_count = 0  # boxes (or tiles) of the region, all members, as its last plan made it
        self._mask: np.ndarray | None = np.zeros((E, *n), dtype=bool)  # the host's copy of `covered` (None: read when asked)
        self.lister = CellLists(self)  # makes ring_list, cover_list and near_list on the device

    # -- host -----------------------------------------------------------------------------
    @property
    def boxes(self) -> "list[list[clustering.Box]] | tiles.MemberBoxes":
        """Each member's region as boxes: Berger–Rigoutsos's, or one per tile (made when asked)."""
        return self._boxes if self.tiles is None else tiles.MemberBoxes(self.mask(), self.tile)

    def box_count(self) -> int:
        """How many boxes the region's last plan made, all members (with tiles: the tiles it covers)."""
        return sum(len(b) for b in self._boxes) if self.tiles is None else self._box_count

    def plan_tiles(self, spde, level: float, keep: float, mean: bool,
                   guard: float = -math.inf) -> tuple[bool, int]:
        """A new region of tiles for every member, flagged on the device by :meth:`Tiles.flag` into
        :attr:`Tiles.target`'s field (the caller's): whether a member's region changed, and how many
        cells were tagged (three counts read back, nothing grid-sized)."""
        tagged, changed, self._box_count = self.tiles.flag(spde, self, level, keep, mean, guard)
        return changed > 0, tagged

    def mask(self) -> np.ndarray:
        """The region of every member, ``(ensemble, *cells)`` booleans: the host's copy, read from the
        device when the region has moved since (a grid-sized read: frames and checkpoints ask, a
        step does not)."""
        if self._mask is None:
            self._mask = self.covered.to_numpy().astype(bool)
        return self._mask.copy()

    def moved(self, masks: np.ndarray | None = None) -> None:
        """``covered`` now holds a new region (``masks``, where the caller has it on the host): the
        lists made again on the device, the host's copy forgotten unless given."""
        self._mask = None if masks is None else np.array(masks, dtype=bool, order="C")
        if masks is not None and self.tiles is not None:
            self._box_count = tiles.count(self._mask, self.tile)
        self.n_ring, self.n_cover = self.lister.make()

    @property
    def ring_mask(self) -> np.ndarray:
        """The ghost cells of every member on the padded grid (padded index = cell index + 1), read
        from the device."""
        return self.lister.ring.to_numpy().astype(bool)

    def plan(self, ppc: np.ndarray) -> tuple[np.ndarray, int]:
        """A new region for every member from its SPDE content ``ppc`` (:func:`clustering.region`;
        members with the same tags are clustered once): the masks, and how many cells were tagged.
        The boxes are kept."""
        masks = np.zeros(ppc.shape, dtype=bool)
        cache: dict[bytes, list] = {}
        tagged = 0
        for e in range(self.ensemble):
            self._boxes[e], masks[e], t = clustering.region(ppc[e], self.params, self.periodic, cache)
            tagged += t
        return masks, tagged

    def plan_extension(self, tags: np.ndarray) -> tuple[np.ndarray, int]:
        """The region plus its uncovered cells among ``tags`` (:func:`clustering.tag` of the content),
        grown by the buffer and clustered: the masks, and how many members
        grew. The new boxes are added to the kept ones. (From the content the caller read for
        the regrid anyway: a device mask of the low cells cost a grid-sized read per extension.)"""
        masks = self.mask()
        low = tags & ~masks
        add = clustering.grow(low, self.params.buffer, (None, *self.periodic))
        members = np.flatnonzero(low.reshape(self.ensemble, -1).any(axis=1))
        for e in members:
            boxes = clustering.cluster(add[e], self.params)
            self._boxes[e] = list(self._boxes[e]) + boxes
            masks[e] |= clustering.mask(boxes, self.n)
        return masks, len(members)

    def grown(self, masks: np.ndarray) -> np.ndarray:
        """The region ``masks`` and its ghost ring (the cells whose particles it keeps)."""
        return clustering.grow(masks, 1, (None, *self.periodic))

    def state(self) -> dict[str, np.ndarray]:
        """The covered mask and every member's boxes (rows ``(member, *lo, *hi)``), for a checkpoint."""
        boxes = [(e, *lo, *hi) for e, bs in enumerate(self.boxes) for lo, hi in bs]
        return {"covered": self.covered.to_numpy(),
                "boxes": np.array(boxes, dtype=np.int64).reshape(-1, 1 + 2 * self.dim)}

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """The region of :meth:`state` back, its lists made again."""
        self.covered.from_numpy(st["covered"])
        self.moved(st["covered"])
        self._boxes = [[] for _ in range(self.ensemble)]
        d = self.dim
        for row in st["boxes"]:
            self._boxes[row[0]].append((tuple(int(v) for v in row[1:1 + d]), tuple(int(v) for v in row[1 + d:])))

    # -- device ---------------------------------------------------------------------------
    @ti.func
    def member(self, e, C):
        """The member-first index ``(e, *C)``."""
        return prefixed(e, C, self.dim)

    @ti.func
    def unflatten(self, i, shape: ti.template()):
        """The index vector of flat (C-order) index ``i`` in an array of ``shape``."""
        d = ti.static(len(shape))
        J = ti.Vector.zero(ti.i32, d)
        for b in ti.static(range(d)):
            a = ti.static(d - 1 - b)
            J[a] = i % shape[a]
            i //= shape[a]
        return J

    @ti.func
    def inside(self, C) -> bool:
        """Whether cell ``C`` (no member index) is a grid cell."""
        ok = True
        for a in ti.static(range(self.dim)):
            ok = ok and 0 <= C[a] < self.n[a]
        return ok

    @ti.func
    def covered_cell(self, i):
        """The member-first index of entry ``i`` of ``cover_list``."""
        return self.unflatten(self.cover_list[i], ti.static(self.covered.shape))

    @ti.func
    def ring_cell(self, i):
        """The member-first index of entry ``i`` of ``ring_list``, and whether it is a grid cell."""
        P = self.unflatten(self.ring_list[i], ti.static(self.lister.ring.shape))
        J = P - 1
        J[0] = P[0]
        return J, self.inside(ti.Vector([J[a + 1] for a in ti.static(range(self.dim))]))

    @ti.kernel
    def count_low(self, spde: ti.template(), trigger: ti.f64, diagnosing: ti.template()):
        """:meth:`count_low_here` in a launch of its own."""
        self.count_low_here(spde, trigger, diagnosing)

    @ti.func
    def count_low_here(self, spde: ti.template(), trigger, diagnosing: ti.template()):
        """Count in :attr:`low` the uncovered cells of ``spde`` holding fewer than ``trigger`` particles
        (content ``q V_c``, or negative): an extension is due when any does (the hybrid's ``extend``;
        read only where one can be: a kernel's return value would sync the device every step). With
        ``diagnosing`` also :meth:`SPDESolver.diagnose` in the same pass (one grid pass, not two).
        Called at a kernel's top level (its loop is then a parallel task): the particle step's
        launch ends with it (:meth:`Coupling.cross`)."""
        if ti.static(diagnosing):
            spde.zero_diagnostics()
        due = 0
        for J in ti.grouped(spde.q):  # the order of SPDESolver.diagnose: the same sums
            content = 0.0
            if ti.static(diagnosing):
                content = spde.diagnose_cell(J)
            else:
                content = ti.cast(spde.q[J], ti.f64) * ti.static(self.grid.cell_volume)
            if not self.covered[J] and content < trigger:
                due += 1
        self.low[None] = due

    @ti.func
    def near(self, e, C):
        """The covered cells within one step of cell ``C`` of member ``e``: bit ``o`` set where cell
        ``C + δ`` is covered (across periodic sides), ``o = Σ_a (δ_a + 1) 3^a`` for ``δ ∈ {−1, 0, 1}^d``,
        ``δ ≠ 0`` (:func:`offset`). A walk step (at most one cell per axis) from ``C`` ends covered
        exactly where it ends at a set offset (:class:`~.crossings.Crossings`). Kept per ring cell
        in :attr:`near_list` while the region stands: its 3^d − 1 lookups made at every fill cost
        the 3D fill 40 %."""
        bits = ti.u32(0)
        for o in range(3**self.dim):  # a loop, not unrolled: less code for the JIT to load
            off = offset(o, self.dim)
            if o != (3**self.dim - 1) // 2:  # δ = 0: the cell itself
                D, ok = wrap(self.grid, C + off)
                if ok:
                    if self.covered[self.member(e, D)] != 0:
                        bits |= ti.u32(1) << ti.u32(o)
        return bits
