"""Berger–Rigoutsos on random and structured tag sets: coverage, efficiency, no overlaps."""
import math

import numpy as np
import pytest

from ti_dk import regrid
from ti_dk.regrid import RegridParams


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
    _check_boxes(tags, regrid.cluster(tags, p), p)


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
    boxes = regrid.cluster(tags, p)
    _check_boxes(tags, boxes, p)
    if tags.all():  # a full 20 x 30 block fits in one box of at most 32 cells a side
        assert len(boxes) == 1


def test_holes_split_disjoint_blobs_exactly():
    p = RegridParams(efficiency=0.9, min_box=2, max_box=64)
    boxes = regrid.cluster(_blobs(), p)
    assert sorted(boxes) == [((2, 3), (10, 20)), ((30, 30), (45, 40))]
    assert regrid.efficiency(boxes, _blobs()) == 1.0


def test_tag_and_grow_respect_periodic_wrap():
    ppc = np.full(10, 20.0)
    ppc[0] = 3.0
    ppc[5] = -0.5  # negative cells are always tagged
    t = regrid.tag(ppc, threshold=5.0)
    assert np.flatnonzero(t).tolist() == [0, 5]
    assert np.flatnonzero(regrid.tag(ppc, threshold=0.0)).tolist() == [5]  # threshold 0: the negative only
    assert np.flatnonzero(regrid.grow(t, 1, (True,))).tolist() == [0, 1, 4, 5, 6, 9]
    assert np.flatnonzero(regrid.grow(t, 2, (False,))).tolist() == [0, 1, 2, 3, 4, 5, 6, 7]
    t2 = np.zeros((6, 6), dtype=bool)
    t2[0, 0] = True  # the corner's Chebyshev neighbours wrap on both axes
    g = regrid.grow(t2, 1, (True, True))
    assert g.sum() == 9 and g[5, 5] and g[1, 5]
