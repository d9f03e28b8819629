"""Where particles are needed: tagging, buffering and Berger–Rigoutsos clustering (paper §3.2).

Host-side NumPy, run once per regrid and member. A box is ``(lo, hi)``, two integer tuples with
``lo <= i < hi`` along every axis, always inside the domain; the particle region is the union
of the boxes, handed to the solvers as a cell mask so that nothing downstream depends on how the
region was cut into boxes.
"""
from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numpy as np

Box = tuple[tuple[int, ...], tuple[int, ...]]


@dataclass(frozen=True)
class RegridParams:
    """Region parameters (paper §3.2; the names follow AMReX).

    ``region``: ``tiles`` (fixed tiles flagged on the device, :mod:`.tiles`) or ``boxes``
    (Berger–Rigoutsos, :func:`cluster`, the paper's); ``tile``: the tiles' side in cells (0: 1 in
    1D, 4 in 2D and 3D); ``release``: a covered tile leaves the region only when all its cells,
    grown by the buffer, hold at least ``release · threshold`` particles (hysteresis);
    ``region_from``: whose density a scheduled regrid tags: ``mean`` (the deterministic q̄ of
    eq. 10, one region for every member, a function of time alone: the hybrid stays exact while
    it moves) or ``member`` (each member's own q: biased while it moves, ``docs/hybrid.md``);
    ``threshold``: tag cells holding fewer particles than this (and every negative cell);
    ``buffer``: grow the tags by this many cells (Chebyshev distance, across periodic sides);
    ``efficiency``: smallest accepted fraction of tagged cells in a box;
    ``min_box`` / ``max_box``: box side limits in cells;
    ``regrid_floor``: between scheduled regrids, when an uncovered cell holds fewer than
    :attr:`trigger` particles, every uncovered cell below ``threshold`` is covered before the next
    step (0, the default: scheduled regrids only; an extension follows the member's own density,
    see ``Regridder.extend``).
    The names are the scene keys' (``grid_efficiency`` is ``efficiency`` here); the schema
    (``scene.schema.HybridKeys``) checks their bounds, so nothing here checks them again.
    """

    threshold: float = 5.0
    buffer: int = 1
    efficiency: float = 0.7
    min_box: int = 2
    max_box: int = 32
    regrid_floor: float = 0.0
    region: str = "tiles"
    tile: int = 0
    release: float = 1.5
    region_from: str = "mean"

    @property
    def trigger(self) -> float:
        """``regrid_floor · threshold``: an uncovered cell holding fewer particles than this makes an
        on-demand extension due (``Region.count_low``)."""
        return self.regrid_floor * self.threshold


def tag(ppc: np.ndarray, threshold: float) -> np.ndarray:
    """Cells whose SPDE content ``ppc`` (particles per cell) is below ``threshold`` (> 0, as the
    schema checked: so every negative cell too). The one tag rule: the regrids, the extensions and
    the work estimate (``scene.estimates``) all call it."""
    return ppc < threshold


def grow(tags: np.ndarray, width: int, periodic: tuple[bool | None, ...]) -> np.ndarray:
    """Tags dilated by ``width`` cells in Chebyshev distance; periodic axes wrap, others clip,
    axes marked None (an ensemble axis) are left alone. (The NumPy form, with ``np.roll``, of the
    face rule the kernels take from ``grid.across``: it dilates whole masks on the host.)"""
    out = tags.copy()
    for a, wrap in enumerate(periodic):
        if wrap is None:
            continue
        base = out.copy()
        for s in range(1, width + 1):
            for shift in (s, -s):
                if wrap:
                    out |= np.roll(base, shift, axis=a)
                else:
                    rolled = np.roll(base, shift, axis=a)
                    edge = [slice(None)] * base.ndim
                    edge[a] = slice(0, shift) if shift > 0 else slice(shift, None)
                    rolled[tuple(edge)] = False
                    out |= rolled
    return out


def cluster(tags: np.ndarray, p: RegridParams) -> list[Box]:
    """Berger–Rigoutsos: cover every tagged cell with disjoint boxes.

    A box is accepted when its tagged fraction reaches ``p.efficiency`` (or it cannot be cut
    into two boxes of at least ``p.min_box`` cells along any axis) and no side exceeds
    ``p.max_box``. Otherwise it is cut, in this order of preference: at a hole in a signature
    (a plane with no tags), at the strongest zero crossing of the signature's second
    difference, else in half along its longest side.

    A box in the making is ``(lo, hi, sigs)``: its bounds as lists, shrunk to its tags, and its
    signatures (tags per plane normal to each axis) as lists of ints. Most boxes are small, and
    NumPy's per-call overhead on them was most of the cost: the cuts now read the signatures in
    plain Python, and a cut costs one reduction, over one of its parts (:func:`_parts`), the
    other's signatures being the parent's minus those.
    """
    boxes: list[Box] = []
    d = tags.ndim
    sig = np.add.reduce(tags, axis=tuple(range(1, d)), dtype=np.intp).tolist()
    if not any(sig):
        return boxes
    root = [0] * d, list(tags.shape), [None] * d
    _shrink(*root, 0, sig)
    for b, s in _signatures(tags, root[0], root[1], 0):
        _shrink(*root, b, s)
    todo = [root]
    while todo:
        lo, hi, sigs = todo.pop()
        size = [b - a for a, b in zip(lo, hi)]
        n = max(size)
        if sum(sigs[0]) / math.prod(size) >= p.efficiency and n <= p.max_box or n < 2 * p.min_box:
            boxes.append((tuple(lo), tuple(hi)))
            continue
        todo += _parts(tags, lo, hi, sigs, *_cut(sigs, size, p))
    return boxes


def _parts(tags: np.ndarray, lo: list[int], hi: list[int], sigs: list[list[int]], axis: int,
           cut: int) -> list[tuple[list[int], list[int], list[list[int]]]]:
    """The two parts, lower then upper, of a box cut along ``axis`` at offset ``cut``, each
    shrunk to its tags, with its signatures. Both hold tags: a box's signatures have tags at
    both ends and ``cut`` is neither 0 nor the side. Along ``axis`` the parts' signatures are
    slices of the box's; along the others, one reduction gives those of the part with fewer
    planes and the other part's are the box's minus these (shrinking a box leaves out planes
    without tags, so its other signatures keep their values)."""
    d, mid = tags.ndim, lo[axis] + cut
    parts = [(lo[:], [*hi[:axis], mid, *hi[axis + 1:]], [None] * d),
             ([*lo[:axis], mid, *lo[axis + 1:]], hi[:], [None] * d)]
    _shrink(*parts[0], axis, sigs[axis][:cut])
    _shrink(*parts[1], axis, sigs[axis][cut:])
    small, large = parts if 2 * cut <= len(sigs[axis]) else parts[::-1]
    for b, s in _signatures(tags, small[0], small[1], axis):
        _shrink(*large, b, list(map(operator.sub, sigs[b], s)))
        _shrink(*small, b, s)
    return parts


def _signatures(tags: np.ndarray, lo: list[int], hi: list[int], axis: int) -> list[tuple[int, list[int]]]:
    """``(b, signature along b)`` of the box ``[lo, hi)`` for every axis ``b`` but ``axis``: one
    pass over the box sums ``axis`` out, the rest are sums over that."""
    rest = np.add.reduce(tags[tuple(map(slice, lo, hi))], axis=axis, dtype=np.intp)
    others = [b for b in range(tags.ndim) if b != axis]
    if len(others) == 1:
        return [(others[0], rest.tolist())]
    return [(b, np.add.reduce(rest, axis=tuple(j for j in range(len(others)) if j != k)).tolist())
            for k, b in enumerate(others)]


def _shrink(lo: list[int], hi: list[int], sigs: list, axis: int, sig: list[int]) -> None:
    """Shrinks the box ``[lo, hi)`` in place along ``axis`` to the planes from the first to the
    last with tags in ``sig``, its signature there, and keeps that slice in ``sigs``."""
    first, end = 0, len(sig)
    while not sig[first]:
        first += 1
    while not sig[end - 1]:
        end -= 1
    sigs[axis] = sig[first:end]
    lo[axis], hi[axis] = lo[axis] + first, lo[axis] + end


def _cut(sigs: list[list[int]], size: list[int], p: RegridParams) -> tuple[int, int]:
    """Axis and offset of the cut for a box of ``size`` that is not accepted (see
    :func:`cluster`), from its signatures ``sigs``. Among equal candidates the first axis, then
    the first plane, wins."""
    m = p.min_box
    longest = size.index(max(size))
    halve = longest, size[longest] // 2  # the first and last resort: halve the longest side
    if size[longest] > p.max_box:  # too long
        return halve
    axes = [a for a, side in enumerate(size) if side >= 2 * m]
    # 1. holes: a plane without tags, closest to the middle of the box (|2i - n|: twice the distance)
    best = None
    for a in axes:
        s, n = sigs[a], size[a]
        if 0 in s:
            for i, v in enumerate(s):
                if not v and m <= i <= n - m and (best is None or abs(2 * i - n) < best[0]):
                    best = (abs(2 * i - n), a, i)
    if best:
        return best[1], best[2]
    # 2. inflection: the largest jump of the second difference where it changes sign
    start = max(m, 2)
    for a in axes:
        s, n = sigs[a], size[a]
        lap = [x - 2 * y + z for x, y, z in zip(s, s[1:], s[2:])]  # lap[i - 1]: at plane i
        jumps = [abs(v - u) if u * v < 0 else 0  # at planes start, start + 1, ... (n - m and n - 2 at most)
                 for u, v in zip(lap[start - 2:n - m - 1], lap[start - 1:n - m])]
        jump = max(jumps, default=0)  # a change of sign jumps by more than 0
        if jump and (best is None or jump > best[0]):
            best = (jump, a, start + jumps.index(jump))
    if best:
        return best[1], best[2]
    return halve  # 3. (at least 2 * min_box: the box was not accepted)


def mask(boxes: list[Box], shape: tuple[int, ...]) -> np.ndarray:
    """The union of ``boxes`` as a boolean cell mask."""
    out = np.zeros(shape, dtype=bool)
    for lo, hi in boxes:
        out[tuple(slice(a, b) for a, b in zip(lo, hi))] = True
    return out


def region(ppc: np.ndarray, p: RegridParams, periodic: tuple[bool, ...],
           cache: dict | None = None) -> tuple[list[Box], np.ndarray, int]:
    """Boxes, cell mask and number of tagged cells (below ``threshold``, before the buffer) of the
    particle region for one member whose SPDE holds ``ppc``. ``cache`` (a dict kept across members)
    clusters each tag pattern once: members with the same tags get the same boxes."""
    low = tag(ppc, p.threshold)
    tags = grow(low, p.buffer, periodic)
    key = tags.tobytes()
    boxes = cache.get(key) if cache is not None else None
    if boxes is None:
        boxes = cluster(tags, p)
        if cache is not None:
            cache[key] = boxes
    return boxes, mask(boxes, ppc.shape), int(low.sum())


def efficiency(boxes: list[Box], tags: np.ndarray) -> float:
    """Tagged cells over covered cells (1 for an empty region)."""
    covered = sum(math.prod(b - a for a, b in zip(lo, hi)) for lo, hi in boxes)
    return float(tags.sum()) / covered if covered else 1.0
