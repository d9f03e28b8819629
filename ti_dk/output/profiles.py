"""Frames of 1D runs: the ensemble's mean, variance, skewness and kurtosis against x.

One PNG per output time (written like the 2D frames, by :class:`ti_dk.output.render.FrameWriter`):
four panels in particles per cell (skewness κ3/κ2^{3/2}, non-excess kurtosis κ4/κ2² + 3), with
the exact answer for particles where the scene has one and the hybrid's particle region shaded
(its height: the fraction of members whose region covers the cell). Exact answers
(:mod:`ti_dk.core.theory`): a periodic domain started from ℓ + Bernoulli(α) particles per cell has
Poisson-binomial counts at every time (each particle moving by the clamped walk); a stationary scene (``t_equil``) with N particles in M
cells, periodic or walled, has Binomial(N, 1/M) counts, or Binomial(N, p_i) with p_i the cell's share of
e^{−U} in a potential.
"""
from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core import theory
from .render import DPI, canvas_rgb, time_label

MOMENTS = ("mean", "variance", "skewness", "kurtosis")
MIN_MEAN = 0.5  # particles per cell: emptier cells do not set the skewness and kurtosis axes
UNITS = {"mean": "mean (particles per cell)", "variance": "variance (particles per cell)²",
         "skewness": "skewness", "kurtosis": "kurtosis (non-excess)"}


class ProfileRenderer:
    """The four moment profiles of a 1D ``scene`` at one time, as an RGB array."""

    def __init__(self, scene):
        if scene.grid.dim != 1:
            raise ValueError("profiles are drawn for 1D scenes")
        self.scene = scene
        self.vol = scene.grid.cell_volume
        n, L = scene.grid.cells[0], scene.grid.lengths[0]
        self.x = (np.arange(n) + 0.5) * (L / n)
        self.edges = np.arange(n + 1) * (L / n)
        self.ppc0 = scene.initial_ppc
        whole = np.allclose(self.ppc0, np.round(self.ppc0))
        periodic = all(side == "periodic" for side in scene.grid.boundary[0])
        closed = all(side in ("periodic", "neumann") for side in scene.grid.boundary[0])
        fixed = whole or scene.method.particle_init != "per_cell"  # a fixed total N of particles
        self.stationary = scene.stats.t_equil is not None and fixed and closed
        self.transient = scene.stats.t_equil is None and periodic and scene.potential is None
        self.fig = Figure(figsize=(11, 7), dpi=DPI)
        FigureCanvasAgg(self.fig)
        self.axes = list(self.fig.subplots(2, 2).flat)
        self.fig.subplots_adjust(left=0.07, right=0.98, bottom=0.07, top=0.91, hspace=0.3, wspace=0.2)

    def exact(self, t: float) -> tuple[dict[str, np.ndarray], str] | tuple[None, None]:
        """The exact per-cell moments of particle counts at ``t`` and their name, or None."""
        if self.stationary:
            n, sc = int(round(self.ppc0.sum())), self.scene
            p = np.full(len(self.x), 1.0 / len(self.x)) if sc.potential is None else \
                sc.potential.boltzmann_weights(sc.grid.cells, sc.grid.lengths)  # each cell's share of e^{-U}
            m = [theory.binomial_moments(n, float(pi)) for pi in p]
            return {k: np.array([mi[k] for mi in m], dtype=float) for k in m[0]}, "exact (binomial)"
        if self.transient and t > 0:
            sc = self.scene
            k = sc.hybrid.particle_substeps if sc.method.name == "hybrid" else 1  # the walk's own step
            return (theory.particle_counts_periodic(self.ppc0, sc.grid.lengths, sc.dt / k, round(t / sc.dt) * k),
                    "exact (Poisson-binomial, clamped walk)")
        return None, None

    def frame(self, t: float, row: dict, region: np.ndarray | None = None) -> np.ndarray:
        """``row``: a statistics row (number densities); ``region``: the fraction of members whose
        particle region covers each cell (hybrid), or None."""
        sc = self.scene
        prof = {"mean": row["mean"] * self.vol, "variance": row["variance"] * self.vol**2,
                "skewness": row["skewness"], "kurtosis": row["kurtosis"]}
        exact, name = self.exact(t)
        samples = int(row["n_samples"])
        what = "samples pooled after t_equil" if sc.stats.t_equil is not None else "members"
        self.fig.suptitle(f"{sc.name}: {sc.method.name}, {samples:,} {what}, {sc.grid.cells[0]} cells     {time_label(t)}",
                          fontsize=12)
        for ax, k in zip(self.axes, MOMENTS):
            ax.clear()
            if region is not None and np.any(region > 0):
                ax.fill_between(self.edges, 0, np.append(region, region[-1]), step="post", color="C3", alpha=0.12,
                                lw=0, transform=ax.get_xaxis_transform(), label="particle region")
            if exact is not None:
                ax.plot(self.x, exact[k], color="0.5", lw=3, alpha=0.6, label=name)
            ax.plot(self.x, prof[k], color="C0", lw=1.2, marker=".", ms=3, label=sc.method.name)
            ax.set(xlabel="x [L]", ylabel=UNITS[k], xlim=(self.edges[0], self.edges[-1]))
            if k in ("skewness", "kurtosis"):  # nearly empty cells have huge moments: range from the rest
                seen = [v[prof["mean"] >= MIN_MEAN] for v in (prof[k], *([exact[k]] if exact else []))]
                seen = np.concatenate(seen)
                seen = seen[np.isfinite(seen)]
                if seen.size:
                    lo, hi = seen.min(), seen.max()
                    pad = 0.08 * (hi - lo) or 0.5
                    ax.set_ylim(lo - pad, hi + pad)
                    ax.set_title(f"range: cells with a mean of {MIN_MEAN:g} particles or more", fontsize=8)
            ax.grid(alpha=0.3)
        self.axes[0].legend(fontsize=9, loc="best")
        return canvas_rgb(self.fig)
