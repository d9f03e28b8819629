"""Offscreen frames: number density panels, particle boxes, negative cells and a colour bar.

Taichi kernels paint an RGB field (no window, no GPU needed); Pillow (an imageio dependency)
adds the text; imageio writes PNGs and movies (MP4 through imageio-ffmpeg, else a GIF).

Layout, 2D: one panel per method side by side (the paper's Figs. 5–6), each the density in
particles per cell on a perceptually uniform colormap (viridis), particle boxes outlined in red,
negative cells as white dots. 3D: one row per method of three mid-plane slices (xy, xz, yz) and a
ray-marched volume rendering; box outlines in black (paper Figs. 7–8), negative cells white.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import taichi as ti
from PIL import Image, ImageDraw, ImageFont

BG = (1.0, 1.0, 1.0)  # page colour
HEADER, LABEL, BAR_W, BAR_GAP, MARGIN = 30, 20, 22, 70, 10  # layout [pixels]


@dataclass
class Panel:
    """What one method shows at one time: density in particles per cell, boxes, region mask."""

    title: str
    ppc: np.ndarray  # (*cells,) particles per cell
    boxes: list = None  # [(lo, hi), ...] in cells (hybrid only)


@ti.func
def _mix(a, b, w):
    return a * (1.0 - w) + b * w


@ti.data_oriented
class Renderer:
    """Paints frames of a grid ``cells`` with ``rows`` methods; densities mapped on [0, vmax]."""

    def __init__(self, cells: tuple[int, ...], rows: int, vmax: float):
        import matplotlib  # the colormap table: viridis, perceptually uniform

        self.cells, self.dim, self.rows, self.vmax = tuple(cells), len(cells), rows, vmax
        target = 512 if self.dim == 2 else 256
        self.s = max(1, target // max(cells))  # pixels per cell
        if self.dim == 2:
            self.panels = [(cells[0], cells[1])]  # (width, height) in cells
        else:
            nx, ny, nz = cells
            self.panels = [(nx, ny), (nx, nz), (ny, nz), (max(cells), max(cells))]
        pw = [w * self.s for w, _ in self.panels]
        self.panel_h = max(h for _, h in self.panels) * self.s
        cols = rows if self.dim == 2 else 1  # 2D: methods side by side; 3D: one row each
        nrows = 1 if self.dim == 2 else rows
        per_row = sum(pw) + MARGIN * (len(pw) - 1)
        self.width = MARGIN + cols * (per_row + MARGIN) + BAR_W + BAR_GAP
        self.width += self.width % 2  # movies need even sizes
        self.height = HEADER + nrows * (self.panel_h + LABEL + MARGIN) + MARGIN
        self.height += self.height % 2
        self.origins = []  # per method: [(x0, y0) of each panel]
        for r in range(rows):
            x = MARGIN + (r * (per_row + MARGIN) if self.dim == 2 else 0)
            y = HEADER + LABEL + (0 if self.dim == 2 else r * (self.panel_h + LABEL + MARGIN))
            row = []
            for w in pw:
                row.append((x, y))
                x += w + MARGIN
            self.origins.append(row)
        self.bar = (self.width - BAR_W - BAR_GAP + 10, HEADER + LABEL)
        lut = matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3]
        self.lut = ti.Vector.field(3, ti.f64, shape=256)  # colormap table
        self.lut.from_numpy(lut)
        self.img = ti.Vector.field(3, ti.f64, shape=(self.width, self.height))  # RGB, y down [0, 1]
        self.font = ImageFont.load_default(size=14)

    # -- public -------------------------------------------------------------------------
    def frame(self, t: float, panels: list[Panel], title: str) -> np.ndarray:
        """One frame as a ``(height, width, 3)`` uint8 array."""
        self.img.fill(ti.Vector(BG))
        labels = []
        for r, p in enumerate(panels):
            neg = int((p.ppc < 0).sum())
            labels.append((self.origins[r][0], f"{p.title}: {neg} negative cell{'s' * (neg != 1)}"
                           + (" · slice xy" if self.dim == 3 else "")))
            if self.dim == 3:
                labels += [(self.origins[r][k], name) for k, name in ((1, "slice xz"), (2, "slice yz"), (3, "volume"))]
            if self.dim == 2:
                self._slice(p.ppc, p.boxes, self.origins[r][0], (0, 1), None)
            else:
                mids = [n // 2 for n in self.cells]
                for k, (axes, fixed) in enumerate((((0, 1), 2), ((0, 2), 1), ((1, 2), 0))):
                    self._slice(p.ppc, p.boxes, self.origins[r][k], axes, (fixed, mids[fixed]))
                self._volume(p.ppc, p.boxes, self.origins[r][3])
        self._bar_kernel(self.bar[0], self.bar[1], BAR_W, self.panel_h)
        rgb = (np.clip(self.img.to_numpy(), 0, 1) * 255 + 0.5).astype(np.uint8).transpose(1, 0, 2)
        return self._text(rgb, t, title, labels)

    # -- host helpers -------------------------------------------------------------------
    def _slice(self, ppc, boxes, origin, axes, cut):
        a, b = axes
        plane = ppc if cut is None else np.take(ppc, cut[1], axis=cut[0])
        rects = []
        for lo, hi in boxes or []:
            if cut is None or lo[cut[0]] <= cut[1] < hi[cut[0]]:
                rects.append((lo[a], lo[b], hi[a], hi[b]))
        rect = np.array(rects, dtype=np.int32).reshape(-1, 4)
        colour = (0.85, 0.05, 0.05) if self.dim == 2 else (0.0, 0.0, 0.0)
        self._paint(np.ascontiguousarray(plane, dtype=np.float32), rect, origin[0], origin[1], self.s,
                    self.vmax, ti.Vector(colour))

    def _volume(self, ppc, boxes, origin):
        cuboids = np.array([(*lo, *hi) for lo, hi in boxes or []], dtype=np.int32).reshape(-1, 6)
        size = self.panels[3][0] * self.s
        self._march(np.ascontiguousarray(ppc, dtype=np.float32), origin[0], origin[1], size, self.vmax)
        self._edges(cuboids, origin[0], origin[1], size)

    def _text(self, rgb, t, title, labels):
        im = Image.fromarray(rgb)
        d = ImageDraw.Draw(im)
        d.text((MARGIN, 7), f"{title}    t = {t:.5g}", fill=(0, 0, 0), font=self.font)
        for r, (xy, text) in enumerate(labels):
            y = xy[1] - LABEL + 2
            d.text((xy[0], y), text, fill=(0, 0, 0), font=self.font)
        x0, y0 = self.bar
        for k in range(5):
            v = self.vmax * k / 4
            y = y0 + self.panel_h - 1 - round((self.panel_h - 1) * k / 4)
            d.line([(x0 + BAR_W, y), (x0 + BAR_W + 4, y)], fill=(0, 0, 0))
            d.text((x0 + BAR_W + 6, y - 8), f"{v:g}", fill=(0, 0, 0), font=self.font)
        d.text((x0 - 6, y0 - LABEL + 2), "ppc", fill=(0, 0, 0), font=self.font)
        return np.asarray(im)

    # -- kernels ------------------------------------------------------------------------
    @ti.func
    def _colour(self, v, vmax):
        k = ti.min(ti.cast(ti.math.clamp(v / vmax, 0.0, 1.0) * 256.0, ti.i32), 255)  # as matplotlib bins it
        return self.lut[k]

    @ti.kernel
    def _paint(self, plane: ti.types.ndarray(), rect: ti.types.ndarray(), x0: ti.i32, y0: ti.i32, s: ti.i32,
               vmax: ti.f64, edge: ti.types.vector(3, ti.f64)):
        """A 2D density (cells ``plane[i, j]``, i right, j up) at ``s`` pixels per cell; negative
        cells as white dots; ``rect`` rows (lo_i, lo_j, hi_i, hi_j) outlined in ``edge``."""
        nx, ny = plane.shape[0], plane.shape[1]
        r = ti.max(1.6, 0.6 * s)  # dot radius [pixels]: visible at a glance however small the cells
        for px, py in ti.ndrange(nx * s, ny * s):
            i, j = px // s, ny - 1 - py // s
            c = self._colour(plane[i, j], vmax)
            for di, dj in ti.static(ti.ndrange((-1, 2), (-1, 2))):  # a white dot on each negative cell
                a, b = i + di, j + dj
                if 0 <= a < nx and 0 <= b < ny and plane[a, b] < 0:
                    cx, cy = (a + 0.5) * s, (ny - b - 0.5) * s
                    if (px + 0.5 - cx) ** 2 + (py + 0.5 - cy) ** 2 <= r * r:
                        c = ti.Vector([1.0, 1.0, 1.0])
            self.img[x0 + px, y0 + py] = c
        w = ti.max(1, s // 3)  # outline width [pixels]
        for k, px, py in ti.ndrange(rect.shape[0], nx * s, ny * s):
            i0, j0, i1, j1 = rect[k, 0] * s, (ny - rect[k, 3]) * s, rect[k, 2] * s, (ny - rect[k, 1]) * s
            if i0 <= px < i1 and j0 <= py < j1:
                if px < i0 + w or px >= i1 - w or py < j0 + w or py >= j1 - w:
                    self.img[x0 + px, y0 + py] = edge

    @ti.kernel
    def _march(self, vol: ti.types.ndarray(), x0: ti.i32, y0: ti.i32, size: ti.i32, vmax: ti.f64):
        """Emission–absorption ray marching through the unit cube, orthographic, seen from
        azimuth 35°, elevation 25°: low density glows (opacity ∝ 1 − q/vmax), so the void and
        what fills it show through the dense background; negative cells glow white."""
        n = ti.Vector([vol.shape[0], vol.shape[1], vol.shape[2]])
        az, el = ti.static(math.radians(35.0), math.radians(25.0))
        F = ti.Vector([ti.cos(el) * ti.cos(az), ti.cos(el) * ti.sin(az), ti.sin(el)])  # towards the viewer
        R = ti.Vector([-ti.sin(az), ti.cos(az), 0.0])
        U = F.cross(R)
        h = 0.5 / ti.cast(n.max(), ti.f32)
        for px, py in ti.ndrange(size, size):
            u = (px + 0.5) / size * 1.8 - 0.9
            v = 0.9 - (py + 0.5) / size * 1.8
            p = ti.Vector([0.5, 0.5, 0.5]) + u * R + v * U + 1.5 * F
            col = ti.Vector([0.0, 0.0, 0.0])
            T = 1.0
            for k in range(ti.cast(3.0 / h, ti.i32)):
                x = p - (k * h) * F
                if 0 <= x[0] < 1 and 0 <= x[1] < 1 and 0 <= x[2] < 1 and T > 0.01:
                    c = ti.cast(x * n, ti.i32)
                    q = vol[c[0], c[1], c[2]]
                    a = 0.0
                    e = self._colour(q, vmax)
                    if q < 0:
                        a = 0.8
                        e = ti.Vector([1.0, 1.0, 1.0])
                    else:
                        a = 1.0 - ti.exp(-4.0 * h * ti.max(0.0, 1.0 - q / vmax) ** 2)
                    col += T * a * e
                    T *= 1.0 - a
            self.img[x0 + px, y0 + py] = col + T * ti.Vector([0.93, 0.93, 0.93])

    @ti.kernel
    def _edges(self, cuboids: ti.types.ndarray(), x0: ti.i32, y0: ti.i32, size: ti.i32):
        """The 12 edges of each box (cells lo..hi of a cube of ``n`` cells) projected as in _march,
        darkening what lies under them (a pixel under several edges once per sample)."""
        az, el = ti.static(math.radians(35.0), math.radians(25.0))
        F = ti.Vector([ti.cos(el) * ti.cos(az), ti.cos(el) * ti.sin(az), ti.sin(el)])
        R = ti.Vector([-ti.sin(az), ti.cos(az), 0.0])
        U = F.cross(R)
        n = ti.cast(ti.static(max(self.cells)), ti.f32)
        for b, e, k in ti.ndrange(cuboids.shape[0], 12, 128):
            lo = ti.Vector([cuboids[b, 0], cuboids[b, 1], cuboids[b, 2]]) / n
            hi = ti.Vector([cuboids[b, 3], cuboids[b, 4], cuboids[b, 5]]) / n
            axis = e // 4  # 4 edges along each axis; the other two coordinates at lo or hi
            c1, c2 = (e % 4) % 2, (e % 4) // 2
            x = lo
            for a in ti.static(range(3)):
                if a == axis:
                    x[a] = lo[a] + (hi[a] - lo[a]) * k / 127.0
                elif (a == (axis + 1) % 3 and c1 == 1) or (a == (axis + 2) % 3 and c2 == 1):
                    x[a] = hi[a]
            d = x - ti.Vector([0.5, 0.5, 0.5])
            px = ti.cast((d.dot(R) + 0.9) / 1.8 * size, ti.i32)
            py = ti.cast((0.9 - d.dot(U)) / 1.8 * size, ti.i32)
            if 0 <= px < size and 0 <= py < size:  # half-transparent: many boxes stay readable
                self.img[x0 + px, y0 + py] *= 0.55

    @ti.kernel
    def _bar_kernel(self, x0: ti.i32, y0: ti.i32, w: ti.i32, hgt: ti.i32):
        for px, py in ti.ndrange(w, hgt):
            self.img[x0 + px, y0 + py] = self.lut[ti.cast((hgt - 1 - py) / (hgt - 1) * 255.0, ti.i32)]


class FrameWriter:
    """PNG frames of a run in ``directory``; optionally a movie of them at the end."""

    def __init__(self, directory: Path, renderer: Renderer, title: str):
        self.dir, self.renderer, self.title = Path(directory), renderer, title
        self.dir.mkdir(parents=True, exist_ok=True)
        self.files: list[Path] = []

    def write(self, t: float, panels: list[Panel]) -> Path:
        rgb = self.renderer.frame(t, panels, self.title)
        path = self.dir / f"frame_{len(self.files):04d}.png"
        iio.imwrite(path, rgb)
        self.files.append(path)
        return path

    def movie(self, fps: int = 8) -> Path:
        """MP4 of all frames (imageio-ffmpeg), or an animated GIF when ffmpeg is absent."""
        frames = [iio.imread(f) for f in self.files]
        try:
            import imageio_ffmpeg  # noqa: F401  (the optional 'movie' extra)
        except ImportError:
            path = self.dir / "movie.gif"
            iio.imwrite(path, np.stack(frames), duration=1000 / fps, loop=0)
            return path
        path = self.dir / "movie.mp4"
        _mp4(path, frames, fps)
        return path


def _mp4(path: Path, frames: list[np.ndarray], fps: int) -> None:
    import imageio.v2 as iio2

    with iio2.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=2) as w:
        for f in frames:
            w.append_data(f)
