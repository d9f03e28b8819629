"""The 3D frames' volume panel: a ray-marched rendering (a Taichi kernel) of translucent shells of
equal density, the particle region as a translucent red hull (paper Figs. 7–8)."""

import math

import numpy as np
import taichi as ti

VIEW = (35.0, 25.0)  # azimuth and elevation of the viewer [degrees]
HULL_RGB = (0.95, 0.35, 0.25)  # colour of the particle region's translucent hull (the 2D frames' box lines)


@ti.data_oriented
class Volume:
    """Ray-marched volume rendering (orthographic, seen from ``VIEW``): translucent shells of equal
    density.

    The density is first averaged over 3³ cells (so the bulk's cell-to-cell noise draws no
    shells); each ray, sampled once per cell length, composites front to back ``C += T a c``,
    ``T ← T (1 − a)``: where it crosses one of the ``LEVELS`` (fractions of the largest initial
    density m) a shell in that level's colour of the colour bar, shaded by its normal (the
    averaged density's gradient), with opacity ``SHELL``; where it crosses the particle region's
    boundary ``HULL_RGB`` with opacity ``HULL`` (a translucent hull); in a negative cell (of the
    unaveraged density) white with opacity ``NEGATIVE``. The void shows as nested shells, a denser
    blob inside it as a shell of its own, and what has filled in as shells moving inwards.
    """

    LEVELS, SHELL, HULL, NEGATIVE = (0.25, 0.6), 0.3, 0.15, 0.5

    def __init__(self, cells, cmap, norm, dense: float):
        self.cells = tuple(cells)
        self.levels = [f * dense for f in self.LEVELS]  # fractions of the largest initial density
        self.rgb = ti.Matrix(cmap(norm(self.levels))[:, :3].tolist())  # each shell's colour: its level's in the bar
        self.img = None  # RGB [0, 1], (size, size): allocated at the first call
        az, el = (math.radians(v) for v in VIEW)
        self.F = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])  # to the viewer
        self.R = np.array([-math.sin(az), math.cos(az), 0.0])
        self.U = np.cross(self.F, self.R)
        self.shape = np.array(self.cells, dtype=float) / max(self.cells)  # the box, longest side 1

    def project(self, p, size: int) -> tuple[float, float]:
        """Pixel (column, row) of the point ``p`` given as a fraction of each side."""
        d = np.asarray(p) * self.shape - 0.5 * self.shape
        return (d @ self.R + 0.9) / 1.8 * size - 0.5, (0.9 - d @ self.U) / 1.8 * size - 0.5

    def render(self, ppc: np.ndarray, region: np.ndarray | None, size: int) -> np.ndarray:
        """The volume panel of ``ppc`` (particles per cell, ``cells``) with the hull of ``region``,
        as RGB in [0, 1], ``(size, size, 3)``."""
        if self.img is None or self.img.shape[0] != size:
            self.img = ti.Vector.field(3, ti.f64, shape=(size, size))  # RGB of the rendering, [0, 1]
        smooth = np.asarray(ppc, dtype=np.float32)
        for a in range(3):  # 3-cell running mean along each axis (periodic images at the sides)
            smooth = (smooth + np.roll(smooth, 1, a) + np.roll(smooth, -1, a)) / 3
        reg = np.zeros(self.cells, np.uint8) if region is None else region.astype(np.uint8)
        self._march(np.ascontiguousarray(ppc, dtype=np.float32), smooth, reg, size, self.rgb,
                    ti.Vector(self.levels), ti.Vector(self.F), ti.Vector(self.R), ti.Vector(self.U),
                    ti.Vector(self.shape))
        return np.clip(self.img.to_numpy().transpose(1, 0, 2), 0, 1)

    @ti.func
    def _at(self, vol: ti.template(), c, n):
        c = ti.math.clamp(c, 0, n - 1)
        return vol[c[0], c[1], c[2]]

    @ti.kernel
    def _march(self, vol: ti.types.ndarray(), avg: ti.types.ndarray(), reg: ti.types.ndarray(), size: ti.i32,
               rgb: ti.types.matrix(2, 3, ti.f64), levels: ti.types.vector(2, ti.f64), F: ti.types.vector(3, ti.f64),
               R: ti.types.vector(3, ti.f64), U: ti.types.vector(3, ti.f64), box: ti.types.vector(3, ti.f64)):
        n = ti.Vector([vol.shape[0], vol.shape[1], vol.shape[2]])
        h = 1.0 / ti.cast(n.max(), ti.f64)  # one cell along the longest axis
        for px, py in ti.ndrange(size, size):
            u = (px + 0.5) / size * 1.8 - 0.9
            v = 0.9 - (py + 0.5) / size * 1.8
            p = u * R + v * U + 1.5 * F
            col = ti.Vector([0.0, 0.0, 0.0])
            T = 1.0
            inside, prev, started = 0, 0.0, 0
            for k in range(ti.cast(3.0 / h, ti.i32)):
                x = (p - (k * h) * F) / box + 0.5  # fraction of each side
                if 0 <= x[0] < 1 and 0 <= x[1] < 1 and 0 <= x[2] < 1 and T > 0.01:
                    c = ti.min(ti.cast(x * n, ti.i32), n - 1)
                    q = ti.cast(avg[c[0], c[1], c[2]], ti.f64)
                    if started:
                        for l in ti.static(range(2)):
                            if (prev - levels[l]) * (q - levels[l]) < 0:  # the ray crosses a shell
                                g = ti.Vector([0.0, 0.0, 0.0])
                                for a in ti.static(range(3)):
                                    e = ti.Vector([0, 0, 0])
                                    e[a] = 1
                                    g[a] = self._at(avg, c + e, n) - self._at(avg, c - e, n)
                                shade = 0.55 + 0.45 * ti.abs(g.normalized(1e-12).dot(F))
                                col += T * self.SHELL * shade * ti.Vector([rgb[l, 0], rgb[l, 1], rgb[l, 2]])
                                T *= 1.0 - self.SHELL
                    r = ti.cast(reg[c[0], c[1], c[2]], ti.i32)
                    if started and r != inside:  # the ray crosses the particle region's boundary
                        col += T * self.HULL * ti.Vector(HULL_RGB)
                        T *= 1.0 - self.HULL
                    if vol[c[0], c[1], c[2]] < 0:
                        col += T * self.NEGATIVE * ti.Vector([1.0, 1.0, 1.0])
                        T *= 1.0 - self.NEGATIVE
                    inside, prev, started = r, q, 1
            self.img[px, py] = col + T * ti.Vector([0.93, 0.93, 0.93])
