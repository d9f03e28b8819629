"""Where particles are needed: tagging, buffering and Berger–Rigoutsos clustering (paper §3.2).

Host-side NumPy, run once per regrid and member. A box is ``(lo, hi)``, two integer tuples with
``lo <= i < hi`` along every axis, always inside the domain; the particle region is the union
of the boxes, handed to the solvers as a cell mask so that nothing downstream depends on how the
region was cut into boxes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Box = tuple[tuple[int, ...], tuple[int, ...]]


@dataclass(frozen=True)
class RegridParams:
    """Clustering parameters (paper §3.2; the names follow AMReX).

    ``threshold``: tag cells holding fewer particles than this (and every negative cell);
    ``buffer``: grow the tags by this many cells (Chebyshev distance, across periodic sides);
    ``efficiency``: smallest accepted fraction of tagged cells in a box;
    ``min_box`` / ``max_box``: box side limits in cells;
    ``floor``: between scheduled regrids, when an uncovered cell holds fewer than ``floor ·
    threshold`` particles, every uncovered cell below ``threshold`` is covered before the next
    step (0: scheduled regrids only; see ``HybridSolver.extend``).
    """

    threshold: float = 5.0
    buffer: int = 1
    efficiency: float = 0.7
    min_box: int = 2
    max_box: int = 32
    floor: float = 1.0


def tag(ppc: np.ndarray, threshold: float) -> np.ndarray:
    """Cells whose SPDE content ``ppc`` (particles per cell) is below ``threshold`` or negative
    (one comparison: below ``max(threshold, 0)``)."""
    return ppc < max(threshold, 0.0)


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
    """
    boxes: list[Box] = []
    todo = [_bounding(tags, (0,) * tags.ndim, tags.shape)]
    while todo:
        found = todo.pop()
        if found is None:
            continue
        box, sigs = found
        lo, hi = box
        size = tuple(b - a for a, b in zip(lo, hi))  # plain ints: most boxes need no array
        if int(sigs[0].sum()) / math.prod(size) >= p.efficiency and max(size) <= p.max_box \
                or max(size) < 2 * p.min_box:
            boxes.append(box)
            continue
        size = np.array(size)
        axis, cut = _cut(sigs, size, size >= 2 * p.min_box, p)
        for part in ((lo, (*hi[:axis], lo[axis] + cut, *hi[axis + 1:])),
                     ((*lo[:axis], lo[axis] + cut, *lo[axis + 1:]), hi)):
            todo.append(_bounding(tags, *part))
    return boxes


def _bounding(tags: np.ndarray, lo, hi) -> tuple[Box, list[np.ndarray]] | None:
    """The smallest box inside ``[lo, hi)`` that holds all its tags, with its signatures (tags
    per plane normal to each axis); None if it has none. Two passes over the box make all the
    signatures (the last axis summed out, then the rest): a box's tagged fraction and its cut
    are read from them, where each used to reduce the box again (the initial sphere3d region
    clustered in 100–114 ms instead of 124–130; ellipse2d 4.3–4.5 instead of 4.7–4.8)."""
    d = tags.ndim
    total = np.add.reduce  # the ufunc itself: ndarray.sum's Python wrapper cost as much as the sums here
    sub = tags[tuple(slice(a, b) for a, b in zip(lo, hi))]
    last = total(sub, axis=tuple(range(d - 1)), dtype=np.intp)
    if not last.any():
        return None
    rows = total(sub, axis=d - 1, dtype=np.intp)
    sigs = [rows, last] if d == 2 else \
        [total(rows, axis=tuple(b for b in range(d - 1) if b != a), dtype=np.intp) for a in range(d - 1)] + [last]
    new_lo, new_hi = [], []
    for a in range(d):
        idx = sigs[a].nonzero()[0]
        first, end = int(idx[0]), int(idx[-1]) + 1
        sigs[a] = sigs[a][first:end]  # the planes outside the box along other axes hold no tags
        new_lo.append(lo[a] + first)
        new_hi.append(lo[a] + end)
    return (tuple(new_lo), tuple(new_hi)), sigs


def _cut(sigs: list[np.ndarray], size: np.ndarray, splittable: np.ndarray, p: RegridParams) -> tuple[int, int]:
    """Axis and offset of the cut for a box that is not accepted (see :func:`cluster`), from its
    signatures ``sigs``. (``nonzero()[0]`` rather than ``np.flatnonzero``: the same for these 1D
    arrays, without its Python wrapper, which cost as much as the work on these small boxes.)"""
    m = p.min_box
    oversize = (size > p.max_box).nonzero()[0]
    if oversize.size:  # too long: halve the longest side first
        a = int(oversize[np.argmax(size[oversize])])
        return a, int(size[a]) // 2
    # 1. holes: a plane without tags, closest to the middle of the box
    best = None
    for a in splittable.nonzero()[0]:
        for i in (sigs[a] == 0).nonzero()[0]:
            if m <= i <= size[a] - m:
                score = abs(i - size[a] / 2)
                if best is None or score < best[0]:
                    best = (score, int(a), int(i))
    if best:
        return best[1], best[2]
    # 2. inflection: the largest jump of the second difference where it changes sign
    best = None
    for a in splittable.nonzero()[0]:
        lap = np.zeros(size[a])
        s = sigs[a].astype(float)
        lap[1:-1] = s[2:] - 2 * s[1:-1] + s[:-2]
        for i in range(max(m, 2), int(size[a]) - m + 1):
            if i < size[a] and lap[i - 1] * lap[i] < 0:
                jump = abs(lap[i] - lap[i - 1])
                if best is None or jump > best[0]:
                    best = (jump, int(a), i)
    if best:
        return best[1], best[2]
    # 3. bisect the longest splittable side
    a = int(splittable.nonzero()[0][np.argmax(size[splittable])])
    return a, int(size[a]) // 2


def mask(boxes: list[Box], shape: tuple[int, ...]) -> np.ndarray:
    """The union of ``boxes`` as a boolean cell mask."""
    out = np.zeros(shape, dtype=bool)
    for lo, hi in boxes:
        out[tuple(slice(a, b) for a, b in zip(lo, hi))] = True
    return out


def region(ppc: np.ndarray, p: RegridParams, periodic: tuple[bool, ...],
           cache: dict | None = None) -> tuple[list[Box], np.ndarray, int]:
    """Boxes, cell mask and number of tagged cells (after the buffer) of the particle region for
    one member whose SPDE holds ``ppc``. ``cache`` (a dict kept across members) clusters each
    tag pattern once: members with the same tags get the same boxes."""
    tags = grow(tag(ppc, p.threshold), p.buffer, periodic)
    key = tags.tobytes()
    boxes = cache.get(key) if cache is not None else None
    if boxes is None:
        boxes = cluster(tags, p)
        if cache is not None:
            cache[key] = boxes
    return boxes, mask(boxes, ppc.shape), int(tags.sum())


def efficiency(boxes: list[Box], tags: np.ndarray) -> float:
    """Tagged cells over covered cells (1 for an empty region)."""
    covered = sum(math.prod(b - a for a, b in zip(lo, hi)) for lo, hi in boxes)
    return float(tags.sum()) / covered if covered else 1.0
