"""Frames checked pixel by pixel: colours of the density, white dots exactly on negative cells,
box outlines around the region, the colour bar."""
import matplotlib
import numpy as np

from ti_dk.render import HEADER, LABEL, MARGIN, Panel, Renderer

VIRIDIS = matplotlib.colormaps["viridis"]


def _rgb(c):
    return np.round(np.asarray(c[:3]) * 255).astype(int)


def test_2d_frame_pixels():
    n, vmax = 16, 10.0
    r = Renderer((n, n), 1, vmax)
    s = r.s
    ppc = np.tile(np.linspace(0, 10, n), (n, 1))  # ppc[i, j] grows with j (upwards)
    negative = [(2, 3), (11, 12), (14, 1)]
    for ij in negative:
        ppc[ij] = -1.0
    box = ((4, 5), (9, 11))
    img = r.frame(0.5, [Panel("hybrid", ppc, [box])], "test").astype(int)
    x0, y0 = MARGIN, HEADER + LABEL

    def centre(i, j):  # pixel of the centre of cell (i, j); j counts upwards
        return img[y0 + (n - 1 - j) * s + s // 2, x0 + i * s + s // 2]

    for i in range(n):
        for j in range(n):
            white = np.all(centre(i, j) == 255)
            assert white == ((i, j) in negative), (i, j)
            if not white and not (box[0][0] <= i < box[1][0] and box[0][1] <= j < box[1][1]):
                assert np.abs(centre(i, j) - _rgb(VIRIDIS(ppc[i, j] / vmax))).max() <= 1
    red = np.array([217, 13, 13])
    (i0, j0), (i1, j1) = box
    left, right = x0 + i0 * s, x0 + i1 * s - 1
    top, bottom = y0 + (n - j1) * s, y0 + (n - j0) * s - 1
    for y in range(top, bottom + 1, 7):
        assert np.all(img[y, left] == red) and np.all(img[y, right] == red)
    for x in range(left, right + 1, 7):
        assert np.all(img[top, x] == red) and np.all(img[bottom, x] == red)
    assert not np.all(img[(top + bottom) // 2, (left + right) // 2] == red)  # outline only
    assert not np.any(np.all(img[:, :x0 + i0 * s - 2] == red, axis=-1))  # nothing red outside the box
    bx, by = r.bar
    assert np.abs(img[by, bx + 5] - _rgb(VIRIDIS(1.0))).max() <= 3  # colour bar: top is vmax
    assert np.abs(img[by + r.panel_h - 1, bx + 5] - _rgb(VIRIDIS(0.0))).max() <= 3
    assert img.shape[0] % 2 == 0 and img.shape[1] % 2 == 0  # movie-safe size


def test_3d_frame_has_slices_and_volume_with_negative_cells():
    n = 12
    x = (np.arange(n) + 0.5) / n - 0.5
    r2 = x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2
    void = np.where(r2 < 0.35**2, 0.0, 8.0)  # an empty ball in a dense background
    ppc = void.copy()
    ppc[6, 6, 6] = -2.0  # in the void, on all three mid-planes
    r = Renderer((n, n, n), 2, 10.0)
    img = r.frame(0.0, [Panel("hybrid", void, [((2, 2, 2), (8, 8, 8))]), Panel("fv", ppc)], "t")
    s = r.s
    for k in range(3):  # the fv row: a white dot at the middle cell of each slice
        x0, y0 = r.origins[1][k]
        assert np.all(img[y0 + (n - 1 - 6) * s + s // 2, x0 + 6 * s + s // 2] == 255)
    x0, y0 = r.origins[0][0]  # the hybrid row: black outline on the xy slice, no white
    assert np.all(img[y0 + (n - 8) * s + 5, x0 + 2 * s] == 0)
    assert not np.any(np.all(img[y0:y0 + n * s, x0:x0 + n * s] == 255, axis=-1))
    # the volume renderings differ only by the negative cell, which glows white through the void
    (hx, hy), (fx, fy) = r.origins[0][3], r.origins[1][3]
    h = r.panel_h
    no_box = r.frame(0.0, [Panel("hybrid", void), Panel("fv", ppc)], "t").astype(int)
    brighter = no_box[fy:fy + h, fx:fx + h].min(axis=-1) - no_box[hy:hy + h, hx:hx + h].min(axis=-1)
    assert brighter.max() > 100 and (brighter > 100).sum() < 0.05 * h * h
