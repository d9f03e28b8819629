"""The particle region as fixed tiles flagged on the device (``region = "tiles"``, the default).

The grid is cut into tiles of ``tile`` cells a side (the last tile along an axis may be cut short
by the grid). One kernel flags every tile of every member from the tag rule of
:func:`clustering.tag` grown by ``buffer`` (:meth:`Tiles.flag`), and the host reads back three
counts; the region, its ring and their lists are made from the flags on the device. Every tile that holds a tag is covered whole, as SAMRAI's ``TileClustering`` and
Uintah's ``TiledRegridder`` make every tile with a tag a box; unlike
Berger–Rigoutsos (:func:`clustering.cluster`, ``region = "boxes"``, the paper's), the region then
follows the tags to within a tile, whatever the box-cutting settings.

Hysteresis: a covered tile stays while any of its cells, grown by ``buffer``, holds fewer than
``release · threshold`` particles, so it leaves only when all are safely above the threshold;
a region whose edge cells fluctuate about the threshold then does not flicker.
"""

import math
from collections.abc import Sequence

import numpy as np
import taichi as ti

from ..core.grid import Grid, wrap
from ..methods.records import small
from .clustering import Box
# tile side in cells where ``tile = 0``, by dimension (1D: the tags exactly), for a region from q̄ and
# from each member's own density. From q̄, 2 in 2D (20 % fewer particles than with 4; 1 is no
# cheaper there) and 1 in 3D (sphere3d 64³ at 300 per cell: half the particles of 2, 1.5× cheaper),
# as the tiles at its edge reach less far into the dense side. Each member's own, 4: its extensions
# come less often (sphere3d 128³: regrids 71 s with 4, 293 s with 2).
# Measured side by side: benchmarks/tile_side.py, benchmarks/RESULTS.md.
DEFAULT_SIDE = {"mean": {1: 1, 2: 2, 3: 1}, "member": {1: 1, 2: 4, 3: 4}}


def side_for(tile: int, cells: tuple[int, ...], region_from: str = "mean") -> int:
    """The tile side in cells: ``tile``, or (0) the default of the grid's dimension and the region's
    source (``region_from``), at most the grid's largest side."""
    return min(tile or DEFAULT_SIDE[region_from][len(cells)], max(cells))


@ti.data_oriented
class Tiles:
    """Tile flags of every member on the device, ``(ensemble, *tiles)`` bytes, and their kernel."""

    def __init__(self, grid: Grid, ensemble: int, side: int, buffer: int):
        self.grid, self.ensemble, self.side, self.buffer = grid, ensemble, side, buffer
        self.dim, self.n = grid.dim, grid.cells
        self.shape = tuple(-(-m // side) for m in self.n)  # tiles per axis
        self.flags = ti.field(ti.u8, shape=(ensemble, *self.shape))  # 1: the tile is in the particle region
        # of the last flag, all members: cells below the threshold, tiles whose cover changed, tiles flagged
        self.counts = ti.field(ti.i32, shape=3)

    def flag(self, spde, region, threshold: float, keep: float, mean: bool, guard: float) -> tuple[int, int, int]:
        """:meth:`_flag`, then its :attr:`counts` (one read of 12 bytes): the cells below
        ``threshold``, the tiles whose cover changed and the tiles flagged, all members."""
        self._flag(spde, region, threshold, keep, mean, guard)
        return tuple(int(c) for c in small(self.counts))

    @ti.func
    def _content(self, spde: ti.template(), region: ti.template(), e, C, mean: ti.template()) -> ti.f64:
        """Cell ``C``'s content ``q V_c`` [particles] in member ``e``, or of q̄ with ``mean``."""
        v = ti.f64(0.0)
        if ti.static(mean):
            v = ti.cast(spde.qbar[region.member(0, C)], ti.f64)
        else:
            v = ti.cast(spde.q[region.member(e, C)], ti.f64)
        return v * self.grid.cell_volume

    @ti.kernel
    def _flag(self, spde: ti.template(), region: ti.template(), threshold: ti.f64, keep: ti.f64,
              mean: ti.template(), guard: ti.f64):
        """Flag each tile of each member: 1 where one of its cells is tagged after the buffer (a cell
        within Chebyshev distance ``buffer`` of it, across periodic sides, holds a content
        ``q V_c`` below ``threshold``: the rule of :func:`clustering.tag`, negative cells included), or
        where the tile is covered now (one of its cells is, in ``region.covered``) and one of its cells
        is within ``buffer`` of a content below ``keep`` (``release · threshold`` at a scheduled
        regrid, hysteresis; infinite at an extension, which only adds tiles). With ``mean`` the
        contents are those of the deterministic q̄ (eq. 10), the same for every member: the region
        then moves as a function of time alone, never of a member's own noise, and the hybrid stays
        exact while it moves (choosing cells by each member's noisy density moves mass across the
        interface: ``benchmarks/moving_region.py``); a tile is then also flagged where one of its
        cells is within ``buffer`` of a cell whose member's own content is below ``guard`` (the
        positivity guard of ``regrid_floor``; −∞: none), so that no tile q̄ releases leaves a
        member's cell below it uncovered. :attr:`counts`: the cells below ``threshold`` themselves
        (before the buffer; the regrid log's efficiency), the tiles whose cells the new flags cover
        otherwise than ``region.covered`` does, and the tiles flagged (the log's boxes)."""
        side, b, d, n = ti.static(self.side, self.buffer, self.dim, self.n)
        W = ti.static(side + 2 * b)  # a tile grown by the buffer, along the last axis
        guarded = guard > -ti.math.inf
        for i in range(3):
            self.counts[i] = 0
        for R in ti.grouped(ti.ndrange(self.ensemble, *self.shape[:-1])):  # a row of tiles along the last axis
            lo = ti.Vector([R[a + 1] * side for a in ti.static(range(d - 1))] + [0])  # its first cell
            end = ti.Vector([ti.min(lo[a] + side, n[a]) for a in ti.static(range(d))])  # past its last (but along the last axis)
            # the least content (q̄'s, the member's own) of the cells within the buffer of the row, by position
            # along the last axis: a window of W of them, slid by a tile (each made once, not once a tile)
            least = ti.Vector([ti.math.inf] * W, dt=ti.f64)
            own = ti.Vector([ti.math.inf] * W, dt=ti.f64)
            for i in ti.static(range(2 * b)):  # the window of tile −1: positions −side − b …, its last 2b made
                least[side + i], own[side + i] = self._column(spde, region, R[0], lo, end, i - b, mean, guarded)
            for t in range(self.shape[d - 1]):
                for i in ti.static(range(2 * b)):
                    least[i], own[i] = least[i + side], own[i + side]
                for i in ti.static(range(side)):
                    least[2 * b + i], own[2 * b + i] = self._column(spde, region, R[0], lo, end, t * side + b + i,
                                                                    mean, guarded)
                K = ti.Vector([R[a] for a in ti.static(range(d))] + [t])
                self._set(spde, region, K, least.min(), own.min(), threshold, keep, guard, mean)

    @ti.func
    def _column(self, spde: ti.template(), region: ti.template(), e, lo, end, k, mean: ti.template(), guarded):
        """The least content ``q V_c`` (q̄'s with ``mean``) and, with ``mean`` and ``guarded``, the least
        of member ``e``'s own, over the cells at position ``k`` of the last axis within the buffer
        of a row of tiles along every other axis (``[lo_a − b, end_a + b)``, across periodic sides);
        none beyond ``n + b`` along the last axis (past a last tile cut short by the grid)."""
        b, d = ti.static(self.buffer, self.dim)
        least, own = ti.math.inf, ti.math.inf
        if k < self.n[d - 1] + b:
            for I in ti.grouped(ti.ndrange(*([self.side + 2 * b] * (d - 1) or [1]))):
                C = lo
                C[d - 1] = k
                near = True
                for a in ti.static(range(d - 1)):
                    C[a] = lo[a] + I[a] - b
                    near = near and C[a] < end[a] + b
                D, ok = wrap(self.grid, C)
                if near and ok:
                    least = ti.min(least, self._content(spde, region, e, D, mean))
                    if ti.static(mean):
                        if guarded:
                            own = ti.min(own, self._content(spde, region, e, D, False))
        return least, own

    @ti.func
    def _set(self, spde: ti.template(), region: ti.template(), K, least, own, threshold, keep, guard,
             mean: ti.template()):
        """Tile ``K``'s flag from the least contents within the buffer of it (:meth:`_column`) and its
        own cells (covered now, and below ``threshold``), with :attr:`counts`."""
        side = ti.static(self.side)
        lo = ti.Vector([K[a + 1] * side for a in ti.static(range(self.dim))])  # the tile's first cell
        end = ti.Vector([ti.min(lo[a] + side, self.n[a]) for a in ti.static(range(self.dim))])  # past its last
        old, whole = False, True
        for I in ti.grouped(ti.ndrange(*([side] * self.dim))):  # the tile's cells
            C = lo + I
            if (C < end).all():
                now = region.covered[region.member(K[0], C)] != 0
                old, whole = old or now, whole and now
                if self._content(spde, region, K[0], C, mean) < threshold:
                    self.counts[0] += 1
        flag = least < threshold or own < guard or (old and least < keep)
        self.flags[K] = ti.u8(flag)
        if flag:
            self.counts[2] += 1
        if (flag and not whole) or (not flag and old):
            self.counts[1] += 1

    @ti.kernel
    def aim(self, target: ti.template()):
        """``target`` (a cell mask, ``(ensemble, *cells)``) set to the region the flags give (:meth:`mask`)."""
        for J in ti.grouped(target):
            K = J
            for a in ti.static(range(self.dim)):
                K[a + 1] = J[a + 1] // self.side
            target[J] = self.flags[K]


def spread(flags: np.ndarray, side: int, n: tuple[int, ...]) -> np.ndarray:
    """Tile flags ``(ensemble, *tiles)`` as the cell mask ``(ensemble, *n)`` they cover."""
    for a, m in enumerate(n):
        flags = np.repeat(flags, side, axis=a + 1).take(range(m), axis=a + 1)
    return flags


def split(masks: np.ndarray, side: int) -> tuple[np.ndarray, np.ndarray]:
    """``masks`` (``(ensemble, *cells)`` booleans) as the tiles they cover whole (``(ensemble,
    *tiles)``; a tile cut short by the grid's edge counts as whole when its cells are covered) and
    the cells they cover in tiles covered in part (a region set from outside,
    :meth:`HybridSolver.set_region`; none where the tiles made the region)."""
    n = masks.shape[1:]
    padded = np.ones((masks.shape[0], *(math.ceil(m / side) * side for m in n)), dtype=bool)
    padded[(slice(None), *(slice(0, m) for m in n))] = masks
    whole = padded.reshape([masks.shape[0], *(s for m in padded.shape[1:] for s in (m // side, side))])
    whole = whole.all(axis=tuple(range(2, 2 * len(n) + 1, 2)))
    return whole, masks & ~spread(whole, side, n)


def boxes(mask: np.ndarray, side: int) -> list[Box]:
    """One member's region (``mask``, a cell mask) as boxes: one per tile it covers whole (cut
    short by the grid's edge), then one per cell of :func:`split`'s part; their union is the region."""
    n = mask.shape
    whole, part = split(mask[None], side)
    return ([(tuple(int(t) * side for t in T), tuple(min((int(t) + 1) * side, m) for t, m in zip(T, n)))
             for T in np.argwhere(whole[0])] + [(tuple(map(int, C)), tuple(int(c) + 1 for c in C))
                                               for C in np.argwhere(part[0])])


def count(masks: np.ndarray, side: int) -> int:
    """How many boxes :func:`boxes` gives, all members."""
    whole, part = split(masks, side)
    return int(whole.sum() + part.sum())


class MemberBoxes(Sequence):
    """Every member's :func:`boxes`, each made when asked (a frame asks for one member's)."""

    def __init__(self, masks: np.ndarray, side: int):
        self.masks, self.side = masks, side

    def __len__(self) -> int:
        return len(self.masks)

    def __getitem__(self, e: int) -> list[Box]:
        return boxes(self.masks[e], self.side)
