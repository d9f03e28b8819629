"""Berger–Rigoutsos on random and structured tag sets: coverage, efficiency, no overlaps."""
import math

import numpy as np
import pytest

from ti_dk.hybrid import clustering
from ti_dk.hybrid.clustering import RegridParams


def _check_boxes(tags, boxes, p):
    cover = np.zeros(tags.shape, dtype=int)
    for lo, hi in boxes:
        assert all(0 <= a < b <= n for a, b, n in zip(lo, hi, tags.shape)), (lo, hi)
        sl = tuple(slice(a, b) for a, b in zip(lo, hi))
        cover[sl] += 1
        size = np.subtract(hi, lo)
        assert np.all(size <= p.max_box), size
        at_minimum = np.all(size < 2 * p.min_box)
        assert tags[sl].mean() >= p.efficiency or at_minimum, (lo, hi, tags[sl].mean())
    assert cover.max() <= 1  # no overlaps
    assert np.all(cover[tags] == 1)  # every tagged cell covered


@pytest.mark.parametrize("shape", [(200,), (40, 50), (12, 13, 14)])
@pytest.mark.parametrize("density", [0.01, 0.1, 0.5])
def test_random_tags(shape, density):
    p = RegridParams(efficiency=0.7, min_box=2, max_box=16)
    tags = np.random.default_rng(math.prod(shape)).random(shape) < density
    _check_boxes(tags, clustering.cluster(tags, p), p)


def _ring(n=64):
    x, y = np.meshgrid(np.arange(n) - n / 2, np.arange(n) - n / 2, indexing="ij")
    return ((x**2 / 400 + y**2 / 100) < 1) & ((x**2 / 150 + y**2 / 40) > 1)


def _blobs():
    t = np.zeros((48, 48), dtype=bool)
    t[2:10, 3:20] = t[30:45, 30:40] = True
    return t


@pytest.mark.parametrize("tags", [_ring(), _blobs(), np.eye(40, dtype=bool), np.ones((20, 30), dtype=bool)],
                         ids=["ellipse ring", "two blobs", "diagonal", "full"])
def test_structured_tags(tags):
    p = RegridParams(efficiency=0.7, min_box=2, max_box=32)
    boxes = clustering.cluster(tags, p)
    _check_boxes(tags, boxes, p)
    if tags.all():  # a full 20 x 30 block fits in one box of at most 32 cells a side
        assert len(boxes) == 1


def test_holes_split_disjoint_blobs_exactly():
    p = RegridParams(efficiency=0.9, min_box=2, max_box=64)
    boxes = clustering.cluster(_blobs(), p)
    assert sorted(boxes) == [((2, 3), (10, 20)), ((30, 30), (45, 40))]
    assert clustering.efficiency(boxes, _blobs()) == 1.0


def _rows(*counts):
    """Tags whose signature along axis 0 is ``counts`` (row i tagged in its first counts[i] of 3
    columns, too few to cut with ``min_box`` 2)."""
    return np.arange(3) < np.array(counts)[:, None]


def _quads():
    t = np.zeros((10, 10), dtype=bool)
    t[:4, :4] = t[:4, 6:] = t[6:, :4] = t[6:, 6:] = True  # the best holes at 5 on both axes
    return t


def _plus():
    t = np.zeros((9, 9), dtype=bool)
    t[3:6, :] = t[:, 3:6] = True  # no hole; equal second-difference jumps at 3 and 6 on both axes
    return t


@pytest.mark.parametrize("tags, efficiency, boxes", [
    (_rows(3, 3, 3, 0, 3, 3, 3, 0, 3, 3), 0.85,  # holes at 3 and 7 (the last: [0, 7) would pass)
     [((8, 0), (10, 3)), ((4, 0), (7, 3)), ((0, 0), (3, 3))]),
    (_quads(), 0.9, [((6, 6), (10, 10)), ((6, 0), (10, 4)), ((0, 6), (4, 10)), ((0, 0), (4, 4))]),
    (_rows(1, 1, 2, 2, 1, 1), 0.7, [((2, 0), (6, 2)), ((0, 0), (2, 1))]),  # equal jumps at 2 and 4
    (_plus(), 0.9, [((6, 3), (9, 6)), ((3, 0), (6, 9)), ((0, 3), (3, 6))]),
], ids=["hole planes", "hole axes", "inflection planes", "inflection axes"])
def test_ties_go_to_the_first_axis_then_plane(tags, efficiency, boxes):
    """Among equal cut candidates the first axis, then the first plane, wins: the boxes and
    their order are pinned on symmetric sets where the other choice gives other boxes or order."""
    assert clustering.cluster(tags, RegridParams(efficiency=efficiency, min_box=2, max_box=32)) == boxes


def test_tag_and_grow_respect_periodic_wrap():
    ppc = np.full(10, 20.0)
    ppc[0] = 3.0
    ppc[5] = -0.5  # negative cells are always tagged
    t = clustering.tag(ppc, threshold=5.0)
    assert np.flatnonzero(t).tolist() == [0, 5]
    assert np.flatnonzero(clustering.tag(ppc, threshold=0.0)).tolist() == [5]  # threshold 0: the negative only
    assert np.flatnonzero(clustering.grow(t, 1, (True,))).tolist() == [0, 1, 4, 5, 6, 9]
    assert np.flatnonzero(clustering.grow(t, 2, (False,))).tolist() == [0, 1, 2, 3, 4, 5, 6, 7]
    t2 = np.zeros((6, 6), dtype=bool)
    t2[0, 0] = True  # the corner's Chebyshev neighbours wrap on both axes
    g = clustering.grow(t2, 1, (True, True))
    assert g.sum() == 9 and g[5, 5] and g[1, 5]
