"""The region of tiles: the device's flags against the tag rule written out in NumPy (buffer,
periodic wrap, hysteresis, tiles cut short by the grid), the blob problem of issue 40, the region
not flickering, and the tiles as boxes."""
import warnings

import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.hybrid import clustering, tiles
from ti_dk.control.registry import make_solver
from ti_dk.scene.load import InputWarning


def _tiles_any(cells, side):
    """``cells`` (``(ensemble, *n)`` booleans) reduced to a flag per tile: any cell set (NumPy)."""
    E, *n = cells.shape
    out = np.zeros((E, *(-(-m // side) for m in n)), dtype=bool)
    for e, *C in np.argwhere(cells):
        out[(e, *(c // side for c in C))] = True
    return out


def _expected(content, old, threshold, keep, side, buffer, periodic):
    """The tile rule from its definition: a tile is flagged where a cell of it, grown by ``buffer``,
    is below ``threshold``, or where it holds a covered cell (``old``) and one below ``keep``; and the
    cells below ``threshold`` themselves (the regrid log's count)."""
    ring = (None, *periodic)
    low = clustering.grow(content < threshold, buffer, ring)
    stay = clustering.grow(content < keep, buffer, ring)
    flags = _tiles_any(low, side) | (_tiles_any(old, side) & _tiles_any(stay, side))
    return tiles.spread(flags, side, content.shape[1:]), int((content < threshold).sum())


def _blob(cells, **kw):
    """Issue 40's new user: a Neumann box, a Gaussian blob of 40 per cell at its centre (σ = 4.8
    cells, as on 96 × 96 at σ = 0.05), nothing around it, threshold 5; the defaults otherwise."""
    sigma = 4.8 / cells
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # void1d's output_times past this t_end
        return load_scene("void1d", init="expression", method="hybrid", cells=[cells, cells], boundary="neumann",
                          density=f"40*exp(-((x-0.5)**2+(y-0.5)**2)/(2*{sigma}**2))", threshold=5,
                          regrid_interval=10, t_end=0.001, ensemble=1, **kw)


def _plan(s, old, side, *args):
    """``Region.plan_tiles`` with the region ``old`` (cells): the masks the flags give (``old`` itself
    where none changed, which plan_tiles says, having counted on the device the tiles that change
    and those flagged: checked here)."""
    s.regions.covered.from_numpy(old.astype(np.uint8))
    moved, tagged = s.regions.plan_tiles(s.spde, *args)
    flags = s.regions.tiles.flags.to_numpy().astype(bool)
    masks = tiles.spread(flags, side, old.shape[1:])
    changed = _touched(masks != old, side, flags.shape)
    counts = s.regions.tiles.counts.to_numpy()
    assert counts[1] == changed.sum() and moved == (changed.sum() > 0)
    assert counts[2] == flags.sum() == s.regions.box_count() == tiles.count(masks, side)
    return masks, tagged


def _touched(cells, side, shape):
    """The tiles (``shape``: ``(ensemble, *tiles)``) holding a cell of ``cells``."""
    out = np.zeros(shape, dtype=bool)
    for e, *C in np.argwhere(cells):
        out[(e, *(c // side for c in C))] = True
    return out


def test_the_blob_core_is_left_to_the_spde_from_the_start():
    # with boxes the region covered every cell (issue 40: 9,216 cells in 16 boxes on 96 × 96)
    scene = _blob(48)
    s = make_solver(scene, scene.initial_ppc)
    content = np.broadcast_to(scene.initial_ppc, (1, 48, 48))[0]  # what the first regrid tags (then sampled)
    region = s.region()[0]
    tagged = clustering.tag(content, 5.0)
    core = ~clustering.grow(tagged, 1, (False, False))  # at or above the threshold beyond the buffer
    assert np.all(region[tagged])  # every tagged cell is covered, and exactly the tiles that hold one
    side = tiles.side_for(0, (48, 48))  # the default: 2
    assert np.array_equal(region, tiles.spread(_tiles_any(~core[None], side), side, (48, 48))[0])
    assert (~region).sum() == 52 * 4  # the core: 52 tiles of 2 × 2 cells (as on 96 × 96 at σ = 0.05)
    boxes = make_solver(_blob(48, region="boxes"), scene.initial_ppc)
    assert boxes.region().all()


@pytest.mark.parametrize("cells,boundary,side,buffer", [
    ((30,), "periodic", 8, 1), ((10, 13), "periodic", 4, 1), ((10, 13), "neumann", 3, 2),
    ((6, 7, 9), ["periodic", "neumann", "dirichlet"], 4, 1)])
def test_flags_follow_the_tag_rule_with_hysteresis(cells, boundary, side, buffer):
    scene = load_scene("void1d", method="hybrid", cells=list(cells), boundary=boundary, ensemble=3, tile=side,
                       buffer=buffer, threshold=5, regrid_interval=0)
    s = make_solver(scene, scene.initial_ppc)
    periodic = s.regions.periodic
    rng = np.random.default_rng(len(cells))
    content = rng.uniform(-1, 12, size=(3, *cells)) ** np.where(rng.uniform(size=(3, *cells)) < 0.9, 1, 2)
    content[1] = 20.0  # a member with no tag: only what it covers and still holds below `keep` stays
    content[1, (0,) * len(cells)] = 6.0
    old = tiles.spread(rng.uniform(size=(3, *(-(-m // side) for m in cells))) < 0.5, side, cells)
    old[2, (0,) * len(cells)] = True  # a region not made of tiles (set from outside): its tile holds it
    s.spde.q.from_numpy(content / s.grid.cell_volume)
    mean = rng.uniform(0, 12, size=(1, *cells))  # q̄ V_c, one for every member
    s.spde.qbar.from_numpy(mean / s.grid.cell_volume)
    for keep in (7.5, 5.0, np.inf):
        masks, tagged = _plan(s, old, side, 5.0, keep, False)
        want, n_low = _expected(content, old, 5.0, keep, side, buffer, periodic)
        assert np.array_equal(masks, want) and tagged == n_low
        if keep == 5.0:  # member 1 holds no cell below 5: it keeps nothing
            assert not masks[1].any()
        # region_from = "mean": every member's tags from q̄, whatever its own q (its own old region kept)
        masks, tagged = _plan(s, old, side, 5.0, keep, True)
        want, n_low = _expected(np.broadcast_to(mean, content.shape), old, 5.0, keep, side, buffer, periodic)
        assert np.array_equal(masks, want) and tagged == n_low
        # with the positivity guard: also each member's tiles near its own cells below 2 (member 1: none)
        masks, tagged = _plan(s, old, side, 5.0, keep, True, 2.0)
        own, _ = _expected(content, np.zeros_like(old), 2.0, keep, side, buffer, periodic)
        assert np.array_equal(masks, want | own) and tagged == n_low and own.any() and not own[1].any()
        # the same again from that region, which keeps all it covers: nothing changes, nothing is read
        assert np.array_equal(_plan(s, masks, side, 5.0, np.inf, True, 2.0)[0], masks)
        assert s.regions.tiles.counts[1] == 0


def test_hysteresis_keeps_the_region_from_flickering():
    # 9 per cell everywhere, threshold 5, a regrid every step: about one cell in 18 is tagged, and
    # a tile of 4 × 4 (6 × 6 with the buffer) is free of tags with probability ≈ 0.1 each time
    # (tags from each member's own density: q̄ = 9 tags nothing).
    # Without hysteresis (release 1) tiles come and go at every regrid; with release 1.5 a tile
    # leaves only when all 36 cells hold 8 or more (≈ 1e-6): none does.
    left = {}
    for release in (1.0, 1.5):
        scene = load_scene("equilibrium1d", method="hybrid", cells=[32, 32], ppc=9, threshold=5, regrid_interval=1,
                           region_from="member", release=release, t_equil=None, histogram=None, seed=3, ensemble=1,
                           tile=4)
        s = make_solver(scene, scene.initial_ppc)
        left[release] = 0
        for n in range(30):
            before = s.region()
            s.step(n)
            left[release] += int((before & ~s.region()).sum())
        assert s.region().mean() > 0.5
    assert left[1.5] == 0 and left[1.0] > 100


@pytest.mark.parametrize("side", [3, 4])
def test_tiles_as_boxes_are_the_region(side):
    masks = tiles.spread(np.random.default_rng(side).uniform(size=(2, 4, 5)) < 0.5, side, (10, 13))
    masks[1, 0, 0] ^= True  # a region not made of tiles: the cells of its partial tile are boxes of one cell
    for e in range(2):
        bs = tiles.boxes(masks[e], side)
        assert np.array_equal(clustering.mask(bs, (10, 13)), masks[e])
        cover = np.zeros((10, 13), dtype=int)
        for lo, hi in bs:
            cover[lo[0]:hi[0], lo[1]:hi[1]] += 1
            assert all(b - a <= side for a, b in zip(lo, hi))
        assert cover.max() == 1
    assert tiles.count(masks, side) == sum(len(tiles.boxes(m, side)) for m in masks)
    assert len(tiles.MemberBoxes(masks, side)) == 2 and tiles.MemberBoxes(masks, side)[1] == tiles.boxes(masks[1], side)
