"""Frames of 2D and 3D runs: density panels with axes, the particle region and its boxes,
negative cells, one colour bar; PNG files and an MP4 movie.

One rendering path: a matplotlib figure (Agg canvas, no window) built once per run and updated
in place for every frame. Each panel is the density of member 0 in particles per cell (not the
number density of the run file's ``/stats``: a frame counts particles), drawn cell for cell
(nearest-neighbour) on viridis over ``[0, vmax]``, the same range in every frame of a run: by
default (:func:`colour_max`) three Poisson standard deviations above the largest density the
run starts from or is fed by (initial condition, Dirichlet reservoirs), so the bulk's
fluctuations show and nothing the run's mean can reach saturates; the scene key ``color_max``
sets it. ``color_scale = "log"`` draws ``[LOG_FLOOR, vmax]`` on a log scale instead (a few
particles leaking beside a thousand per cell show), 0 to ``LOG_FLOOR`` in its lowest colour.
Denser cells take the top colour (the colour bar's upper arrow) and negative cells are white (its
lower arrow), exactly one cell in size at any resolution.

The particle region (the union of the hybrid's boxes; the cell mask's outline) is outlined in
black inside a white line, visible on every colour, its Berger–Rigoutsos boxes inside it as thin
red lines (``BOX``; a region of tiles shows its outline only, the density inside left clear), a
hole in it (uncovered cells no path of face neighbours outside the region links to the domain's
edge, :func:`holes`) by a dotted black line on white. Each side is labelled
with its boundary kind (:func:`side_labels`). 2D: one panel per method side by side (the paper's
Figs. 5–6), an external potential's contours in white, every 2 k_BT up to 12 above its least
value, each labelled with its k_BT. 3D: one row per method of three mid-plane slices (xy, xz, yz)
and a volume rendering (:class:`ti_dk.output.volume.Volume`). Lengths are in the scene's length
unit L, times in L²/(2D) (the code's units: D = ½).
"""

import math
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure

from .files import frame_file
from .volume import HULL_RGB, Volume
from ..hybrid.clustering import mask as region_mask

DPI = 100  # figure pixels per inch: sizes below are in pixels
LEFT, GAP, TOP, ROW_HEAD, BOTTOM, BAR = 56, 62, 34, 22, 42, 84  # layout [pixels]
OUTLINE = [dict(color="white", lw=2.6, capstyle="projecting"), dict(color="black", lw=1.0, capstyle="projecting")]
HOLE = [dict(color="white", lw=2.2, capstyle="butt"), dict(color="black", lw=1.2, linestyle=(0, (1.2, 1.2)))]
BOX = dict(color=HULL_RGB, lw=0.8)  # the region's boxes: thin red lines (the 3D hull's colour)
LOG_FLOOR = 0.1  # particles per cell: the bottom of a log colour scale (0 to it: the lowest colour)
POTENTIAL_KT = tuple(range(2, 13, 2))  # U's contours: these many k_BT above its least value


@dataclass
class Panel:
    """What one method shows at one time: density in particles per cell and its particle boxes."""

    title: str
    ppc: np.ndarray  # (*cells,) particles per cell
    boxes: list | None = None  # [(lo, hi), ...] in cells (hybrid only)
    tiles: bool = False  # the boxes are the region's tiles: only the region's outline is drawn


def colour_max(ppc0: np.ndarray, reservoirs=()) -> float:
    """Top of the colour range [particles per cell]: the largest density m of the initial
    condition ``ppc0`` and the Dirichlet ``reservoirs`` plus three Poisson standard deviations,
    rounded up to a multiple of 5 (1 below 10 particles per cell).

    The mean density solves the diffusion equation, which never exceeds its largest initial or
    boundary value (maximum principle), so one fixed range serves the whole run: the same colour
    is the same density in every frame, and only cells more than 3σ above m saturate.
    """
    m = max([float(np.max(ppc0)) if np.size(ppc0) else 0.0, *map(float, reservoirs)])
    v = m + 3.0 * math.sqrt(max(m, 0.0))
    step = 5.0 if v > 10 else 1.0
    return max(step, step * math.ceil(v / step))


def time_label(t: float) -> str:
    """``t = 9.60×10⁻⁴ L²/(2D)``: three significant digits and the unit (mathtext)."""
    if t == 0:
        return r"$t = 0\ L^2/(2D)$"
    e = math.floor(math.log10(abs(t)))
    m = t / 10.0**e
    if round(m, 2) >= 10:
        m, e = m / 10, e + 1
    body = f"{m:.2f}" if e == 0 else rf"{m:.2f}\times10^{{{e}}}"
    return rf"$t = {body}\ L^2/(2D)$"


def canvas_rgb(fig: Figure) -> np.ndarray:
    """Draw ``fig`` (on an Agg canvas) and return its pixels, ``(height, width, 3)`` uint8."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def outline(region: np.ndarray, dx: tuple[float, float]) -> np.ndarray:
    """Segments ``(k, 2, 2)`` in domain units along the boundary of a 2D cell mask (its cells
    ``region[i, j]``; the domain's edge counts as outside), collinear cell edges merged."""
    m = np.pad(np.asarray(region, dtype=bool), 1)
    segs = []
    for axis in (0, 1):  # edges normal to this axis: between cells i-1 and i along it
        diff = (m[1:, 1:-1] != m[:-1, 1:-1]) if axis == 0 else (m[1:-1, 1:] != m[1:-1, :-1]).T
        runs = np.diff(np.pad(diff, ((0, 0), (1, 1))).astype(np.int8), axis=1)
        (i, j0), (_, j1) = np.nonzero(runs == 1), np.nonzero(runs == -1)
        a, b = dx if axis == 0 else dx[::-1]
        s = np.stack([np.stack([i * a, j0 * b], -1), np.stack([i * a, j1 * b], -1)], 1)
        segs.append(s if axis == 0 else s[..., ::-1])
    return np.concatenate(segs).astype(float)


def holes(region: np.ndarray) -> np.ndarray:
    """The holes of a 2D cell mask: cells outside it from which no path of face neighbours
    outside it reaches the domain's edge (periodic sides count as edges, so a region that wraps
    around the domain has no hole through the seam)."""
    free = ~np.asarray(region, dtype=bool)
    reach = np.zeros_like(free)  # free cells linked to the edge
    for edge in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1]):
        reach[edge] = free[edge]
    while True:
        grown = reach.copy()
        grown[1:] |= reach[:-1]
        grown[:-1] |= reach[1:]
        grown[:, 1:] |= reach[:, :-1]
        grown[:, :-1] |= reach[:, 1:]
        grown &= free
        if np.array_equal(grown, reach):
            return free & ~reach
        reach = grown


def box_edges(boxes, axes: tuple[int, int], dx: tuple[float, ...], cut: int | None = None,
              at: int = 0) -> np.ndarray:
    """Segments ``(4k, 2, 2)`` in domain units: the sides of the ``k`` boxes ``(lo, hi)`` (cells,
    hi exclusive) seen in the plane of ``axes``; with ``cut``, only the boxes that hold cell
    ``at`` along that axis (a slice through the cell centres of layer ``at``)."""
    a, b = axes
    segs = []
    for lo, hi in boxes:
        if cut is not None and not lo[cut] <= at < hi[cut]:
            continue
        x0, x1, y0, y1 = lo[a] * dx[a], hi[a] * dx[a], lo[b] * dx[b], hi[b] * dx[b]
        segs += [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
    return np.array(segs, dtype=float).reshape(-1, 2, 2)


def side_labels(boundary, reservoir_ppc) -> tuple[tuple[str, str], ...]:
    """Per axis, the (lower, upper) sides' boundary kinds as the frames write them: ``periodic``,
    ``neumann`` or ``dirichlet ρ=40/cell`` (the reservoir in particles per cell)."""
    def label(kind: str, ppc: float) -> str:
        return f"dirichlet ρ={ppc:g}/cell" if kind == "dirichlet" else kind

    return tuple((label(k0, r0), label(k1, r1)) for (k0, k1), (r0, r1) in zip(boundary, reservoir_ppc))


def dirichlet_ppc(boundary, reservoir_ppc) -> list[float]:
    """The reservoir densities [particles per cell] of the Dirichlet sides (for :func:`colour_max`)."""
    return [r for kinds, ppcs in zip(boundary, reservoir_ppc) for k, r in zip(kinds, ppcs) if k == "dirichlet"]


class Renderer:
    """Frames of a grid of ``cells`` (lengths ``lengths``) with ``rows`` methods, densities on ``[0, vmax]``
    particles per cell, headed by ``title``; ``sides``: per axis the (lower, upper) sides' labels
    (:func:`side_labels`; None: none); ``dense``: 3D, the largest initial density that the volume
    rendering's shell levels are fractions of (None: m with m + 3√m = vmax); ``potential``: U;
    ``log``: the colour scale is logarithmic, from ``LOG_FLOOR`` (or vmax/10 below it) to vmax."""

    def __init__(self, cells, lengths, rows: int, vmax: float, title: str, sides=None, dense=None, potential=None,
                 log: bool = False):
        self.cells, self.lengths = tuple(int(n) for n in cells), tuple(float(v) for v in lengths)
        self.dim, self.rows, self.vmax, self.title = len(self.cells), rows, float(vmax), title
        self.sides, self.potential = sides, potential  # U(x, y) drawn as labelled contours in 2D (None: none)
        m = (math.sqrt(9 / 4 + self.vmax) - 1.5) ** 2 if dense is None else dense  # m + 3√m = vmax
        self.dx = tuple(L / n for L, n in zip(self.lengths, self.cells))
        target = 512 if self.dim == 2 else 256  # pixels along the longest side of a panel
        self.s = max(1, target // max(round(L / min(self.dx)) for L in self.lengths))  # pixels per finest cell
        self.ppu = self.s / min(self.dx)  # pixels per unit length
        self.cmap = matplotlib.colormaps["viridis"].with_extremes(under="white", bad="white")  # LogNorm: <= 0 is bad
        self.log = log
        self.norm = LogNorm(min(LOG_FLOOR, self.vmax / 10), self.vmax) if log else Normalize(0.0, self.vmax)
        if self.dim == 3:
            self.planes = (((0, 1), 2), ((0, 2), 1), ((1, 2), 0))  # (shown axes, cut axis)
            self.volume = Volume(self.cells, self.cmap, self.norm, m)
        else:
            self.planes = (((0, 1), None),)
        self._layout()

    @classmethod
    def of(cls, scene, compared: bool = False) -> "Renderer":
        """The frames of a 2D or 3D ``scene`` (with ``compared``, its ``compare`` method beside or
        below): colour range ``color_max``, or if 0 :func:`colour_max` of the initial density and the
        Dirichlet reservoirs, on the scale ``color_scale``; each side labelled with its boundary kind."""
        g, m = scene.grid, scene.method
        methods = m.name + (f" (left) and {m.compare} (right)" if compared and g.dim == 2 else
                            f" (top) and {m.compare} (bottom)" if compared else "")
        ppc0 = scene.initial_ppc
        vmax = scene.output.color_max or colour_max(ppc0, dirichlet_ppc(g.boundary, g.reservoir_ppc))
        return cls(g.cells, g.lengths, 1 + compared, vmax,
                   f"{scene.name}: {methods}, {'×'.join(map(str, g.cells))} cells, member 0",
                   side_labels(g.boundary, g.reservoir_ppc), float(np.max(ppc0)), scene.potential,
                   scene.output.color_scale == "log")

    # -- layout (once) ------------------------------------------------------------------
    def _size(self, axes) -> tuple[int, int]:
        return tuple(round(self.lengths[a] * self.ppu) for a in axes)

    def _layout(self):
        sizes = [self._size(axes) for axes, _ in self.planes]
        if self.dim == 3:
            side = max(max(w, h) for w, h in sizes)
            sizes.append((side, side))
        panel_h = max(h for _, h in sizes)
        cols = self.rows if self.dim == 2 else 1  # 2D: methods side by side; 3D: one row each
        nrows = 1 if self.dim == 2 else self.rows
        row_w = sum(w for w, _ in sizes) + GAP * (len(sizes) - 1)
        self.width = LEFT + cols * row_w + (cols - 1) * GAP + BAR + 10
        row_h = ROW_HEAD * (self.dim == 3) + 18 + panel_h + BOTTOM
        self.height = TOP + nrows * row_h
        self.width += self.width % 2  # movies need even sizes
        self.height += self.height % 2
        W, H = self.width, self.height
        self.fig = Figure(figsize=(W / DPI, H / DPI), dpi=DPI)
        FigureCanvasAgg(self.fig)
        size = 11 if W > 900 else 8.5  # one panel: the title and the time share a narrow header
        self.header = self.fig.text(10 / W, 1 - 8 / H, "", va="top", fontsize=size)
        self.clock = self.fig.text(1 - 10 / W, 1 - 8 / H, "", va="top", ha="right", fontsize=size)
        self.axes, self.images, self.lines, self.row_titles = [], [], [], []
        self.pixels = []  # per method: (left, top, width, height) of each panel in image pixels
        for r in range(self.rows):
            x = LEFT + (r * (row_w + GAP) if self.dim == 2 else 0)
            top = TOP + (0 if self.dim == 2 else r * row_h) + ROW_HEAD * (self.dim == 3) + 18
            if self.dim == 3:
                self.row_titles.append(self.fig.text(10 / W, 1 - (top - 18 - ROW_HEAD + 4) / H, "", va="top",
                                                     fontsize=10, fontweight="bold"))
            row_axes, row_images, row_lines = [], [], []
            self.pixels.append([])
            for k, (w, h) in enumerate(sizes):
                ax = self.fig.add_axes((x / W, 1 - (top + h) / H, w / W, h / H))
                self.pixels[r].append((x, top, w, h))
                x += w + GAP
                row_axes.append(ax)
                image, lines = self._panel(ax, k, w, h)
                row_images.append(image)
                if lines is not None:
                    row_lines.append(lines)
            self.axes.append(row_axes)
            self.images.append(row_images)
            self.lines.append(row_lines)
        self._colorbar()
        self._mark_dynamic()

    def _panel(self, ax, k, w: int, h: int):
        """Panel ``k`` of a row: a slice (image and region outlines) or, past the slices, the volume."""
        if k == len(self.planes):  # the volume rendering
            image = ax.imshow(np.zeros((h, w, 3)), interpolation="nearest", resample=False)
            ax.set_axis_off()
            self._cube_edges(ax, w)
            return image, None
        (a, b), cut = self.planes[k]
        ext = (0, self.lengths[a], 0, self.lengths[b])
        image = ax.imshow(np.zeros((self.cells[b], self.cells[a])), origin="lower", extent=ext, cmap=self.cmap,
                          norm=self.norm, interpolation="nearest", resample=False, aspect="auto")
        lines = [ax.add_collection(LineCollection([], **style)) for style in (BOX, *OUTLINE, *HOLE)]
        names = "xyz"
        ax.set_xlabel(f"{names[a]} [L]", labelpad=1)
        ax.set_ylabel(f"{names[b]} [L]", labelpad=1)
        ax.tick_params(labelsize=8, length=3, pad=2)
        if self.sides is not None:
            self._side_labels(ax, a, b)
        if self.potential is not None and self.dim == 2:
            lines += self._contours(ax)
        if cut is not None:
            c = (self.cells[cut] // 2 + 0.5) * self.dx[cut]
            ax.set_title(f"{names[a]}{names[b]} slice, {names[cut]} = {c:.3g} L", fontsize=9)
        return image, lines

    def _contours(self, ax) -> list:
        """U's contours ``POTENTIAL_KT`` k_BT above its least value on the grid, in white, each
        labelled with its k_BT (none for a flat U): the contour set and its labels, drawn over the
        density after the 5 lines that :meth:`_slices` sets."""
        x, y = ((np.arange(n) + 0.5) * h for n, h in zip(self.cells, self.dx))
        u = self.potential(x[:, None], y[None, :])
        u0 = float(np.min(u))
        levels = [u0 + k for k in POTENTIAL_KT if u0 + k < np.max(u)]
        if not levels:
            return []
        cs = ax.contour(x, y, u.T, levels=levels, colors="white", linewidths=0.6, alpha=0.55)
        labels = ax.clabel(cs, fontsize=7, colors="white", fmt=lambda v: rf"${v - u0:.0f}\,k_BT$")
        return [cs, *labels]

    def _side_labels(self, ax, a: int, b: int):
        """Each side's boundary kind at the ends of the axis labels' lines: the lower and upper
        sides of axis ``a`` below the panel's left and right ends, those of ``b`` left of its
        bottom and top."""
        style = dict(xycoords="axes fraction", textcoords="offset pixels", fontsize=7.5, color="0.25")
        for end, ha in ((0, "left"), (1, "right")):
            ax.annotate(self.sides[a][end], (end, 0), (0, -19), ha=ha, va="top", **style)
        for end, va in ((0, "bottom"), (1, "top")):
            ax.annotate(self.sides[b][end], (0, end), (-34, 0), ha="center", va=va, rotation=90, **style)

    def _colorbar(self):
        """The colour bar beside the panels, from the top of the first row to the bottom of the last."""
        W, H = self.width, self.height
        first, last = self.axes[0][0], self.axes[-1][0]
        y0, y1 = last.get_position().y0, first.get_position().y1
        cx = (self.width - BAR + 6) / W
        cax = self.fig.add_axes((cx, y0, 14 / W, y1 - y0))
        self.bar_pixels = (self.width - BAR + 6, round((1 - y1) * H), 14, round((y1 - y0) * H))
        sm = matplotlib.cm.ScalarMappable(self.norm, self.cmap)
        cb = self.fig.colorbar(sm, cax=cax, extend="both", extendfrac=0.04)
        cb.set_label(f"particles per cell{', log scale' * self.log} (white: < 0)", fontsize=9)
        cax.tick_params(labelsize=8)

    def _mark_dynamic(self):
        """What changes from frame to frame is drawn over a cached picture of the rest (axes, ticks,
        labels, colour bar): text is most of a frame's cost, and the ticks never change."""
        self.dynamic = [self.header, self.clock, *self.row_titles]
        for r in range(self.rows):
            for k, ax in enumerate(self.axes[r]):
                if k == len(self.planes):  # the volume panel: no ticks, redrawn whole
                    self.dynamic.append(ax)
                else:  # the frame lines go over the image, as in a full draw
                    self.dynamic += [self.images[r][k], *self.lines[r][k], ax.title, *ax.spines.values()]
        for artist in self.dynamic:
            artist.set_animated(True)
        self.background = None  # the static parts, rendered at the first frame

    def _cube_edges(self, ax, size):
        """The domain's 12 edges, faint, and the axis names, projected as the volume rendering."""
        P = self.volume.project
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
        for p in range(8):
            for q in range(p + 1, 8):
                if np.abs(corners[p] - corners[q]).sum() == 1:
                    (x0, y0), (x1, y1) = P(corners[p], size), P(corners[q], size)
                    ax.plot([x0, x1], [y0, y1], color="0.55", lw=0.6)
        for a, name in enumerate("xyz"):
            tip = np.zeros(3)
            tip[a] = 1.12
            x, y = P(tip, size)
            ax.text(x, y, name, fontsize=9, ha="center", va="center", color="0.3")
        ax.set_xlim(-0.5, size - 0.5)
        ax.set_ylim(size - 0.5, -0.5)

    # -- one frame ----------------------------------------------------------------------
    def frame(self, t: float, panels: list[Panel]) -> np.ndarray:
        """One frame as a ``(height, width, 3)`` uint8 array."""
        self.header.set_text(f"{self.title}; density in particles per cell")
        self.clock.set_text(time_label(t))
        for r, p in enumerate(panels):
            ppc = np.asarray(p.ppc)
            neg = int((ppc < 0).sum())
            region = region_mask(p.boxes, self.cells) if p.boxes is not None else None
            any_hole = self._slices(r, p, ppc, region)
            text = f"{p.title}: {neg:,} negative cell{'s' * (neg != 1)}"
            if region is not None:
                what = f"tile{'s' * (len(p.boxes) != 1)}" if p.tiles else f"box{'es' * (len(p.boxes) != 1)} (red)"
                text += (f"; particle region {int(region.sum()):,} cells in {len(p.boxes)} {what}"
                         f"{'; holes dotted' * any_hole}")
            if self.dim == 2:
                self.axes[r][0].set_title(text, fontsize=9.5)
            else:
                self.row_titles[r].set_text(text)
            if self.dim == 3:
                lv = " and ".join(f"{v:.3g}" for v in self.volume.levels)
                self.axes[r][3].set_title(f"volume: shells at {lv} per cell" + (
                    "\nparticle region: translucent red hull" if region is not None else ""), fontsize=8.5)
                size = self.images[r][3].get_array().shape[0]
                self.images[r][3].set_data(self.volume.render(ppc, region, size))
        return self._draw()

    def _slices(self, r: int, p: Panel, ppc: np.ndarray, region: np.ndarray | None) -> bool:
        """Method ``r``'s density slices (the whole grid in 2D), with the region's boxes, outer edge
        and holes' edges; whether a slice shows a hole."""
        mids = [n // 2 for n in self.cells]
        any_hole = False
        for k, ((a, b), cut) in enumerate(self.planes):
            plane = ppc if cut is None else np.take(ppc, mids[cut], axis=cut)
            if self.log:  # LogNorm draws values <= 0 white ("bad"): 0 to the floor take the lowest colour
                plane = np.where(plane < 0, plane, np.maximum(plane, self.norm.vmin))
            self.images[r][k].set_data(plane.T)
            segs = [np.zeros((0, 2, 2))] * 3  # boxes, the region's outer edge, its holes' edges
            if region is not None:
                rplane = region if cut is None else np.take(region, mids[cut], axis=cut)
                hole, d = holes(rplane), (self.dx[a], self.dx[b])
                any_hole |= bool(hole.any())
                at = mids[cut] if cut is not None else 0
                boxes = segs[0] if p.tiles else box_edges(p.boxes, (a, b), self.dx, cut, at)  # tiles: outline only
                segs = [boxes, outline(rplane | hole, d), outline(hole, d)]
            for lc, s in zip(self.lines[r][k], segs[:1] + segs[1:2] * 2 + segs[2:] * 2):  # as (BOX, *OUTLINE, *HOLE)
                lc.set_segments(s)
        return any_hole

    def _draw(self) -> np.ndarray:
        canvas = self.fig.canvas
        if self.background is None:
            canvas.draw()  # everything but the animated artists
            self.background = canvas.copy_from_bbox(self.fig.bbox)
        else:
            canvas.restore_region(self.background)
        for artist in self.dynamic:
            self.fig.draw_artist(artist)
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()


class FrameWriter:
    """PNG frames of a run in ``directory`` (``frame_0000.png`` …) and, at the end, an MP4."""

    def __init__(self, directory: Path, renderer):
        self.dir, self.renderer = Path(directory), renderer
        self.dir.mkdir(parents=True, exist_ok=True)
        self.files: list[Path] = []

    def write(self, t: float, *content) -> Path:
        """Render ``renderer.frame(t, *content)`` to the next PNG."""
        rgb = self.renderer.frame(t, *content)
        path = frame_file(self.dir, len(self.files))
        path.unlink(missing_ok=True)  # a new file, never written through a link
        iio.imwrite(path, rgb, compress_level=1)  # fast deflate: a third of the time of the default, files ~1.3x
        self.files.append(path)
        return path

    def movie(self, path: Path, fps: int = 8) -> Path:
        """An H.264 MP4 of all frames at ``path`` (imageio-ffmpeg ships its own ffmpeg)."""
        import imageio.v2 as iio2

        with iio2.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=2) as w:
            for f in self.files:
                w.append_data(iio.imread(f))
        return Path(path)
