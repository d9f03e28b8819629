"""Frames read back pixel by pixel: density colours, negative cells inside their own cell, axes and
ticks, region outlines on the darkest and brightest colours, the region's boxes and its holes,
boundary labels, one colour bar, the 3D volume panel, and the MP4 a run writes beside its file."""
import subprocess
import sys

import imageio.v3 as iio
import matplotlib
import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.output.render import (BOX, Panel, Renderer, box_edges, colour_max, dirichlet_ppc, holes, outline,
                                 side_labels, time_label)

VIRIDIS = matplotlib.colormaps["viridis"]


def _rgb(c):
    return np.round(np.asarray(c[:3]) * 255).astype(int)


def _lum(px):
    return np.asarray(px, dtype=float) @ [0.299, 0.587, 0.114]


def _cell(r, img, i, j, n, k=0, row=0):
    """Pixels of cell (i, j) (j counts upwards) of panel k of method ``row`` (two pixels inside its
    edges where cells are 8 pixels or more)."""
    x0, y0, w, h = r.pixels[row][k]
    a, b = x0 + i * w / n, y0 + (n - 1 - j) * h / n
    m = 2 if w / n >= 8 else 0
    return img[round(b) + m:round(b + h / n) - m, round(a) + m:round(a + w / n) - m]


@pytest.mark.parametrize("n", [32, 256])
def test_2d_colours_and_negative_cells_inside_their_own_cell(n):
    vmax = 40.0
    r = Renderer((n, n), (1.0, 1.0), 1, vmax, "test")
    ppc = np.tile(np.linspace(0, vmax, n), (n, 1))  # ppc[i, j] grows with j (upwards)
    negative = [(2, 3), (n // 2, n - 3), (n - 2, 1), (n - 3, 1)]  # off the border: the frame covers its pixels
    for ij in negative:
        ppc[ij] = -1.0
    img = r.frame(0.5, [Panel("fv", ppc)]).astype(int)
    for i, j in negative:
        assert np.all(_cell(r, img, i, j, n) == 255), (i, j)
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):  # the neighbours keep their colour
            a, b = i + di, j + dj
            if 0 < a < n - 1 and 0 < b < n - 1 and (a, b) not in negative:
                px = _cell(r, img, a, b, n)
                assert np.abs(px - _rgb(VIRIDIS(ppc[a, b] / vmax))).max() <= 2, (a, b)
    for i, j in ((5, 7), (n - 3, n // 3), (n // 2, n // 2)):
        assert np.abs(_cell(r, img, i, j, n) - _rgb(VIRIDIS(ppc[i, j] / vmax))).max() <= 2
    assert img.shape[0] % 2 == 0 and img.shape[1] % 2 == 0  # movie-safe size


def test_2d_axes_have_ticks_and_labels_in_domain_units():
    n = 64
    r = Renderer((n, n), (2.0, 1.0), 1, 10.0, "test")  # a 2 x 1 domain: panel twice as wide as high
    img = r.frame(0.0, [Panel("fv", np.full((n, n), 5.0))]).astype(int)
    x0, y0, w, h = r.pixels[0][0]
    assert abs(w - 2 * h) <= 1
    dark = _lum(img) < 100
    below = dark[y0 + h + 1:y0 + h + 4]  # tick marks just under the lower axis line
    ticks = r.axes[0][0].get_xticks()
    assert ticks[0] == 0.0 and ticks[-1] == 2.0 and len(ticks) >= 3  # domain units: 0 to 2
    for x in ticks:
        assert below[:, round(x0 + w * x / 2.0) - 1:round(x0 + w * x / 2.0) + 2].any(), x
    between = round(x0 + w * (ticks[0] + ticks[1]) / 4.0)
    assert not below[:, between - 1:between + 2].any()  # marks, not a line
    assert dark[y0 + h + 6:y0 + h + 20, x0 - 5:x0 + w + 5].sum() > 50  # tick labels
    left = dark[:, x0 - 4:x0 - 1]  # tick marks left of the panel
    yticks = r.axes[0][0].get_yticks()
    assert yticks[0] == 0.0 and yticks[-1] == 1.0
    for y in yticks:
        row = round(y0 + h - h * y)
        assert left[row - 2:row + 2].any(), y
    assert dark[y0:y0 + h, x0 - 40:x0 - 6].sum() > 30  # y tick labels and label


def test_region_outline_shows_on_the_darkest_and_brightest_colours():
    n, vmax = 32, 40.0
    r = Renderer((n, n), (1.0, 1.0), 1, vmax, "test")
    ppc = np.zeros((n, n))
    ppc[n // 2:] = 2 * vmax  # left half darkest (0), right half brightest (above the range)
    box = ((8, 8), (24, 24))  # straddles both halves
    img = r.frame(0.0, [Panel("hybrid", ppc, [box])]).astype(int)
    x0, y0, w, h = r.pixels[0][0]
    s = w / n
    top = round(y0 + (n - 24) * s)  # the box's upper edge, in image rows
    band = lambda x: _lum(img[top - 4:top + 5, round(x)])  # noqa: E731  a column across that edge
    dark_bg, bright_bg = _lum(_rgb(VIRIDIS(0.0))), _lum(_rgb(VIRIDIS(1.0)))
    for x in (x0 + 10.5 * s, x0 + 14.5 * s):  # on the darkest colour: a light line
        assert band(x).max() > dark_bg + 150
    for x in (x0 + 18.5 * s, x0 + 22.5 * s):  # on the brightest colour: a dark line
        assert band(x).min() < bright_bg - 150
    inside = _cell(r, img, 12, 16, n)
    assert np.abs(inside - _rgb(VIRIDIS(0.0))).max() <= 2  # the box is outlined, not filled


def test_outline_follows_the_mask_and_merges_edges():
    m = np.zeros((6, 5), dtype=bool)
    m[1:4, 1:3] = True  # a 3 x 2 block ...
    m[1, 3] = True      # ... with one cell on top: an L-shape, perimeter 12 cell edges, 6 straight runs
    segs = outline(m, (0.5, 1.0))
    lengths = np.abs(segs[:, 1] - segs[:, 0]).sum(axis=1)
    assert len(segs) == 6
    assert np.isclose(lengths.sum(), 2 * 3 * 0.5 + 2 * 3 * 1.0)  # 6 edges of 0.5 along x, 6 of 1.0 along y
    assert np.isclose(segs[..., 0].min(), 0.5) and np.isclose(segs[..., 0].max(), 2.0)
    assert len(outline(np.zeros((4, 4), bool), (1.0, 1.0))) == 0


def test_colour_range_and_time_label():
    assert colour_max(np.array([0.0, 30.0])) == 50.0  # 30 + 3√30 = 46.4, up to a multiple of 5
    assert colour_max(np.array([4.0])) == 10.0
    assert colour_max(np.zeros(3)) == 1.0
    assert colour_max(np.array([30.0]), [40.0, 0.0]) == 60.0  # a 40-per-cell reservoir: 40 + 3√40 = 59.0
    assert time_label(0.00096035) == r"$t = 9.60\times10^{-4}\ L^2/(2D)$"
    assert time_label(0.0) == r"$t = 0\ L^2/(2D)$" and time_label(2.5) == r"$t = 2.50\ L^2/(2D)$"



@pytest.mark.parametrize("panels", [1, 2])
def test_every_frame_shows_its_own_time_inside_the_picture(panels):
    """The time is redrawn on every frame (an artist left out of the blitted ones keeps the first
    frame's time) and lies inside the frame however narrow (one panel)."""
    n = 16
    r = Renderer((n, n), (1.0, 1.0), panels, 10.0, "doublewell2d: hybrid, 16×16 cells, member 0")
    ppc = np.full((n, n), 5.0)
    one, two = (r.frame(t, [Panel("fv", ppc)] * panels) for t in (0.0, 1.5e-3))
    header = slice(0, 24)
    assert np.abs(one[header].astype(int) - two[header]).sum() > 0
    assert r.clock.get_text() == time_label(1.5e-3)
    box = r.clock.get_window_extent(r.fig.canvas.get_renderer())
    assert 0 <= box.x0 and box.x1 <= r.width and r.header.get_window_extent().x1 < box.x0

def test_colour_range_and_side_labels_of_a_scene():
    walled = dict(cells=[16, 16], boundary=[["dirichlet", "neumann"], "periodic"], reservoir_ppc=[[40, 5], 0])
    r = Renderer.of(load_scene("ellipse2d", **walled))  # initial density 30 at most, reservoir 40
    assert r.vmax == 60.0 and r.rows == 1
    assert r.sides == (("dirichlet ρ=40/cell", "neumann"), ("periodic", "periodic"))
    assert Renderer.of(load_scene("ellipse2d", color_max=80.0, **walled), compared=True).vmax == 80.0
    assert Renderer.of(load_scene("ellipse2d", cells=[16, 16])).vmax == 50.0  # no reservoir: from the initial 30
    assert dirichlet_ppc([["dirichlet", "dirichlet"], ["neumann", "periodic"]], [[3.0, 7.0], [9.0, 9.0]]) == [3.0, 7.0]
    assert side_labels([["periodic", "periodic"]], [[0.0, 0.0]]) == (("periodic", "periodic"),)


def test_boundary_kinds_are_written_beside_each_side():
    n = 32
    sides = (("dirichlet ρ=40/cell", "neumann"), ("periodic", "periodic"))
    ppc = np.full((n, n), 5.0)
    plain, labelled = (Renderer((n, n), (1.0, 1.0), 1, 10.0, "test", s) for s in (None, sides))
    a, b = (r.frame(0.0, [Panel("fv", ppc)]).astype(int) for r in (plain, labelled))
    x0, y0, w, h = labelled.pixels[0][0]
    differ = np.abs(a - b).max(axis=-1) > 60
    assert not differ[y0:y0 + h, x0:x0 + w].any()  # nothing drawn over the density
    below = differ[y0 + h + 18:y0 + h + 32]  # the line of the axis label, under the tick labels
    assert below[:, x0:x0 + w // 3].sum() > 40 and below[:, x0 + 2 * w // 3:x0 + w].sum() > 20  # both ends
    assert not below[:, x0 + w // 3 + 20:x0 + 2 * w // 3 - 20].any()  # the middle keeps the axis name alone
    left = differ[y0:y0 + h, x0 - 42:x0 - 26]  # left of the y tick labels
    assert left[:h // 3].sum() > 20 and left[2 * h // 3:].sum() > 20  # top and bottom ends


def _red(px):
    """Pixels close to the boxes' colour (a red none of viridis's colours is near)."""
    return np.abs(np.asarray(px, dtype=int) - _rgb(BOX["color"])).max(axis=-1) < 60


# a ring of four boxes round a hole of 8 x 10 cells, on a 32 x 32 grid (cells (i, j), j upwards)
RING = [((4, 4), (28, 10)), ((4, 10), (10, 20)), ((18, 10), (28, 20)), ((4, 20), (28, 26))]


def test_boxes_are_drawn_inside_the_region_and_holes_are_dotted():
    n, vmax = 32, 40.0
    r = Renderer((n, n), (1.0, 1.0), 1, vmax, "test")
    ppc = np.full((n, n), 2 * vmax)  # the brightest colour everywhere: lines are what is not yellow
    img = r.frame(0.0, [Panel("hybrid", ppc, RING)]).astype(int)
    x0, y0, w, h = r.pixels[0][0]
    s = w / n  # pixels per cell
    X = lambda i: round(x0 + i * s)  # noqa: E731  image column of the cell edge x = i
    Y = lambda j: round(y0 + h - j * s)  # noqa: E731  image row of the cell edge y = j
    # box sides inside the region: y = 10 between the lowest box and the side ones, y = 20 between
    # the side ones and the top one
    for j, (i0, i1) in ((10, (4, 10)), (10, (18, 28)), (20, (4, 10)), (20, (18, 28))):
        for x in np.linspace(X(i0) + 0.3 * s, X(i1) - 0.3 * s, 6).round().astype(int):
            assert _red(img[Y(j) - 2:Y(j) + 3, x]).any(), (j, x)
    assert not _red(_cell(r, img, 7, 15, n)).any() and not _red(_cell(r, img, 15, 7, n)).any()  # not filled
    assert not _red(img[y0:y0 + h, x0:X(3)]).any()  # nothing outside the region

    def darkest(j, i0, i1):  # per column along the edge y = j (its ends left out): the darkest pixel
        cols = range(X(i0) + round(s), X(i1) - round(s))
        return np.array([_lum(img[Y(j) - 3:Y(j) + 4, x]).min() for x in cols])

    outer, hole = darkest(4, 4, 28), darkest(10, 10, 18)  # the region's lower edge; the hole's
    assert outer.max() < 90  # a continuous black line
    assert 0.2 < (hole < 90).mean() < 0.8 and hole.max() > 200  # black dots on white
    assert not _red(img[Y(10) - 1:Y(10) + 2, X(10) + round(s):X(18) - round(s)]).any()  # no box line there
    assert "holes dotted" in r.axes[0][0].get_title() and "particles per cell" in r.header.get_text()
    # the same region as tiles: its outline and holes as before, no tile drawn inside it
    img = r.frame(0.0, [Panel("hybrid", ppc, RING, tiles=True)]).astype(int)
    assert not _red(img[y0:y0 + h, x0:x0 + w]).any() and darkest(4, 4, 28).max() < 90
    assert "in 4 tiles;" in r.axes[0][0].get_title()


def test_holes_and_box_edges_from_a_mask_set_by_hand():
    m = np.zeros((8, 7), dtype=bool)
    m[1:6, 1:6] = True
    m[2:4, 2:4] = False  # a 2 x 2 hole ...
    m[4, 5] = False  # ... and a notch open to the outside (through the cell (4, 6))
    expect = np.zeros_like(m)
    expect[2:4, 2:4] = True
    assert np.array_equal(holes(m), expect)
    assert not holes(np.ones((4, 4), bool)).any() and not holes(np.zeros((4, 4), bool)).any()
    edge = np.ones((5, 5), bool)
    edge[0, 2] = False  # on the domain's edge: not a hole
    assert not holes(edge).any()
    segs = box_edges([((1, 2), (3, 5))], (0, 1), (0.5, 0.25))
    assert np.allclose(segs[0], [[0.5, 0.5], [1.5, 0.5]]) and len(segs) == 4
    assert np.isclose(np.abs(segs[:, 1] - segs[:, 0]).sum(), 2 * (1.0 + 0.75))  # the box's perimeter
    boxes3 = [((0, 0, 2), (4, 4, 6)), ((0, 0, 6), (4, 4, 8))]
    assert len(box_edges(boxes3, (0, 1), (1.0,) * 3, cut=2, at=5)) == 4  # only the first holds layer 5
    assert len(box_edges(boxes3, (0, 2), (1.0,) * 3, cut=1, at=3)) == 8


def _spheres(n, inner):
    x = (np.arange(n) + 0.5) / n - 0.5
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    void = X**2 + Y**2 + Z**2 < 0.35**2
    ppc = np.where(void, 0.0, 30.0)
    if inner:
        ppc[(X - 0.1) ** 2 + (Y - 0.1) ** 2 + Z**2 < 0.12**2] = 15.0
    return ppc, void


def test_3d_volume_shows_the_density_through_the_region_and_one_colour_bar():
    n = 24
    r = Renderer((n, n, n), (1.0, 1.0, 1.0), 2, colour_max(np.array([30.0])), "test")
    plain, void = _spheres(n, inner=False)
    dense, _ = _spheres(n, inner=True)
    boxes = [((3, 3, 3), (21, 21, 21))]  # the region covers the void
    x, y, w, h = r.pixels[0][3]
    vol = lambda img: img[y:y + h, x:x + w].astype(float)  # noqa: E731
    a = vol(r.frame(0.0, [Panel("hybrid", plain, boxes), Panel("fv", plain)]))
    b = vol(r.frame(0.0, [Panel("hybrid", dense, boxes), Panel("fv", dense)]))
    c = vol(r.frame(0.0, [Panel("hybrid", plain), Panel("fv", plain)]))
    background = a[2:10, 2:10].reshape(-1, 3)
    changed = np.abs(b - a).max(axis=-1) > 20  # the denser sphere inside the void, seen through the region
    assert changed.sum() > 0.005 * w * h
    cy, cx = np.argwhere(changed).mean(axis=0)
    assert abs(cx - w / 2) < 0.3 * w and abs(cy - h / 2) < 0.3 * h  # near the middle, where the void is
    assert np.abs(a - c).max(axis=-1).sum() > 0  # the region's hull is drawn ...
    assert (np.abs(a - c).max(axis=-1) > 30).sum() < 0.5 * (np.abs(a - background.mean(0)).max(-1) > 30).sum()
    # ... and covers far less than the density shows
    bx, by, bw, bh = r.bar_pixels  # one colour bar from the top of the first row to the bottom of the last
    img = r.frame(0.0, [Panel("hybrid", plain, boxes), Panel("fv", plain)]).astype(int)
    top, bottom = r.pixels[0][0][1], r.pixels[1][0][1] + r.pixels[1][0][3]
    assert abs(by - top) <= 1 and abs(by + bh - bottom) <= 1
    col = img[by:by + bh, bx + bw // 2]
    assert col[round(0.15 * bh), 1] > 180 and _lum(col[round(0.85 * bh)]) < 80  # yellow above, purple below


def test_3d_slices_mark_negative_cells_and_outline_the_region():
    n = 16
    r = Renderer((n, n, n), (1.0, 1.0, 1.0), 1, 50.0, "test")
    ppc, _ = _spheres(n, inner=False)
    ppc[8, 8, 8] = -2.0  # on all three mid-planes
    img = r.frame(0.0, [Panel("hybrid", ppc, [((4, 4, 4), (12, 12, 12))])]).astype(int)
    for k in range(3):
        assert np.all(_cell(r, img, 8, 8, n, k) == 255), k
    x0, y0, w, h = r.pixels[0][0]
    edge = img[y0 + h // 4 - 4:y0 + h // 4 + 4, x0 + w // 2]  # the region's upper edge in the xy slice
    assert _lum(edge).max() > 200 and _lum(edge).min() < 60  # light and dark lines together


def test_movie_is_an_mp4_beside_the_run_file_and_printed(tmp_path):
    r = subprocess.run([sys.executable, "-m", "ti_dk.scene", "ellipse2d", "--set", "cells=[16,16]", "--t-end", "0.002",
                        "--set", "output_times=[0.002]", "--movie", "--set", "movie_frames=4", "--no-snapshots",
                        "--no-progress", "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    mp4 = tmp_path / "ellipse2d_hybrid.mp4"
    assert str(mp4) in r.stdout and str(tmp_path / "ellipse2d_hybrid_frames") in r.stdout
    pngs = sorted((tmp_path / "ellipse2d_hybrid_frames").glob("frame_*.png"))
    assert len(pngs) == 5  # 8 steps: steps 0, 2, 4, 6 and 8 (the output time)
    frames = iio.imread(mp4, plugin="pyav") if _has("av") else iio.imread(mp4, index=None)
    assert frames.shape[0] == 5 and frames.shape[1:] == iio.imread(pngs[0]).shape
    assert not list((tmp_path / "ellipse2d_hybrid_frames").glob("*.gif"))


def _has(module):
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def test_a_potential_is_drawn_as_contours_labelled_with_their_k_bt_in_2d():
    """U's contours, 2 to 12 k_BT above its least value, over each 2D panel, each labelled with its
    k_BT (contours and labels drawn in every frame: they go with the artists drawn over the cached
    picture); none without U."""
    from matplotlib.contour import ContourSet
    from matplotlib.text import Text

    def contours(scene):
        r = Renderer.of(scene, compared=True)
        return [[a for a in r.lines[m][0] if isinstance(a, (ContourSet, Text))] for m in range(r.rows)]

    with_u = contours(load_scene("doublewell2d", cells=[16, 16], C=0.008))
    for drawn in with_u:
        (cs,), labels = [a for a in drawn if isinstance(a, ContourSet)], [a for a in drawn if isinstance(a, Text)]
        u0 = min(cs.levels) - 2  # U = 2 (x-0.3)^2 (x-0.7)^2 + ... / 5e-4 on the cell centres
        assert list(np.round(cs.levels - u0, 9)) == [2, 4, 6, 8, 10, 12] and cs.get_animated()
        kts = {t.get_text() for t in labels}
        assert kts <= {rf"${k}\,k_BT$" for k in (2, 4, 6, 8, 10, 12)} and len(kts) >= 4, kts
        assert all(t.get_animated() for t in labels)
    assert contours(load_scene("ellipse2d", cells=[16, 16])) == [[], []]


def test_log_colour_scale_maps_decades_and_keeps_negative_cells_white():
    """color_scale = "log": equal steps in log density are equal steps of colour, 0 to the floor takes
    the lowest colour, and negative cells stay white."""
    n, vmax = 32, 1000.0
    r = Renderer((n, n), (1.0, 1.0), 1, vmax, "test", log=True)
    ppc = np.full((n, n), 10.0)
    ppc[4, 4], ppc[8, 8], ppc[12, 12], ppc[16, 16], ppc[20, 20] = 1.0, 100.0, 0.0, -3.0, 0.05
    img = r.frame(0.0, [Panel("fv", ppc)]).astype(int)
    assert r.norm.vmin == 0.1 and r.norm.vmax == vmax
    for (i, j), v in (((4, 4), 1.0), ((8, 8), 100.0), ((2, 2), 10.0), ((12, 12), 0.1), ((20, 20), 0.1)):
        frac = (np.log10(v) + 1) / 4  # 0.1 to 1000: four decades
        assert np.abs(_cell(r, img, i, j, n) - _rgb(VIRIDIS(frac))).max() <= 2, (i, j)
    assert np.all(_cell(r, img, 16, 16, n) == 255)
    assert Renderer.of(load_scene("doublewell2d", cells=[16, 16], C=0.008)).log  # the scene asks for it
    assert not Renderer.of(load_scene("ellipse2d", cells=[16, 16])).log


FRAME_CELLS = {1: None, 2: [16, 16], 3: [8, 8, 8]}  # small grids: the layout is the same at any size


@pytest.mark.parametrize("name", ["doublewell2d", "ellipse2d", "equilibrium1d", "sphere3d", "trap1d", "void1d",
                                  "doublewell2d linear"])
def test_no_text_of_any_shipped_scenes_frame_leaves_the_figure(name, monkeypatch):
    """Every text drawn in a frame (titles, tick labels, the colour bar's label, side labels, contour
    labels) lies inside the figure: its window extent inside the figure's box."""
    from matplotlib.text import Text
    from ti_dk.output.profiles import ProfileRenderer
    from ti_dk.scene.load import available_scenes

    assert set(available_scenes()) <= {"doublewell2d", "ellipse2d", "equilibrium1d", "sphere3d", "trap1d", "void1d"}
    scene_name, *scale = name.split()  # "linear": the frame, on the scene's 64x64 (up to 1,070 per cell)
    dim = load_scene(scene_name).grid.dim
    extra = dict(C=0.008) if scene_name == "doublewell2d" else {}  # stable on 16x16
    sc = load_scene(scene_name, **extra, **({"cells": FRAME_CELLS[dim]} if FRAME_CELLS[dim] and not scale else {}),
                    **({"color_scale": scale[0]} if scale else {}))
    drawn = []
    draw = Text.draw

    def recording(self, renderer):
        draw(self, renderer)
        if self.get_visible() and self.get_text():
            drawn.append((self, renderer))

    monkeypatch.setattr(Text, "draw", recording)
    ppc = sc.initial_ppc
    if dim == 1:
        r = ProfileRenderer(sc)
        v = sc.grid.cell_volume
        row = dict(mean=ppc / v, variance=ppc / v**2, skewness=1 / np.sqrt(ppc + 1), kurtosis=3 + 1 / (ppc + 1),
                   n_samples=sc.method.ensemble)
        r.frame(sc.time.t_end, row, np.where(ppc < ppc.mean(), 1.0, 0.0))
        fig = r.fig
    else:
        r = Renderer.of(sc, compared=sc.method.compare is not None)
        box = [(tuple(0 for _ in sc.grid.cells), tuple(n // 2 for n in sc.grid.cells))]
        r.frame(sc.time.t_end, [Panel(sc.method.name, ppc, box)] + [Panel(sc.method.compare, ppc)] * (r.rows - 1))
        fig = r.fig
    W, H = fig.bbox.width, fig.bbox.height
    assert len(drawn) > 10
    out = [(t.get_text(), e.bounds) for t, ren in drawn for e in [t.get_window_extent(ren)]
           if e.x0 < -0.5 or e.y0 < -0.5 or e.x1 > W + 0.5 or e.y1 > H + 0.5]
    assert not out, (W, H, out)
