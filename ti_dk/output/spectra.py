"""The static structure factor S(k) of a run's last statistics row drawn against |k|, with its exact
answer where there is one: ``structure_factor.png`` beside the frames.

S(k) is defined in :mod:`ti_dk.core.spectra`. 1D: every mode ``m = 1 … M/2``; 2D/3D: the modes
binned by |k| in shells one ``2π/max(L_a)`` wide (estimate and exact answer binned alike, since
the lattice's answer is not isotropic). Below it, (estimate − exact)/SE per point, the SE that of
independent samples (:func:`ti_dk.core.spectra.relative_se`; time samples of a pooled row are
correlated, so its true error is larger).

Exact answers (periodic box, uniform start, :mod:`ti_dk.core.theory`): particles
(:func:`~ti_dk.core.theory.particle_structure_factor`: 1 for ``exact_uniform``, the walk's
relaxation from the per-cell start otherwise); ``gaussian`` (the linear scheme,
:func:`~ti_dk.core.theory.linear_structure_factor`, exact); ``fv`` (the same linear answer, to
a relative ≈ 1/(8ρ): :func:`exact_structure_factor`). The hybrid is drawn without one.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core import spectra, theory
from .render import DPI, time_label


def exact_structure_factor(scene, steps) -> tuple[np.ndarray | None, str]:
    """The exact S(k) of ``scene``'s method on the kept half grid for a row made of the samples at
    ``steps`` (an int, or the steps pooled), and its name; ``(None, "")`` where there is none.

    There is one for a uniform start in a periodic box: the particles' (exact); ``gaussian``'s
    (exact: its noise amplitude is q̄'s, which stays uniform); ``fv``'s, the linear scheme's too.
    FV's step is linear in q but for its noise amplitude, and Z is independent of q, so its second
    moments follow the linear recursion with the face variance ``⟨A²⟩``, ``A = (√q_L + √q_R)/2``,
    in place of ρ (counts): S_fv = (⟨A²⟩/ρ) S_lin, and expanding the roots to second order,
    ``⟨A²⟩ ≈ ρ − (σ² − c)/(8ρ) ≈ ρ − 1/8`` (σ² the cell variance ≈ ρ, c the neighbours' covariance
    ≈ 0): FV lies ≈ 1/(8ρ) below, 0.1 % at 100 particles per cell.
    """
    grid, name = scene.grid, scene.method.name
    ppc = scene.initial_ppc
    periodic = all(side == "periodic" for sides in grid.boundary for side in sides)
    if not periodic or not np.allclose(ppc, ppc.flat[0]) or ppc.flat[0] <= 0:
        return None, ""
    if name == "particle":
        start = None if scene.method.particle_init == "exact_uniform" else steps
        return spectra.half(theory.particle_structure_factor(float(ppc.flat[0]), grid.cells, grid.lengths,
                                                             scene.dt, start)), "exact (particles)"
    if name in ("fv", "gaussian"):
        c = tuple(scene.dt / (L / n) ** 2 for L, n in zip(grid.lengths, grid.cells))
        return spectra.half(theory.linear_structure_factor(grid.cells, c, steps)), "exact (linear scheme)"
    return None, ""


def radial_bins(cells: tuple[int, ...], lengths: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Per kept mode, its |k| shell index (−1: k = 0 or a duplicate of another mode), and the
    shells' mean |k|; 1D: one shell per mode."""
    kk = spectra.magnitude(cells, lengths)
    use = spectra.independent_modes(cells) & (kk > 0)
    width = 2 * np.pi / max(lengths)
    shell = np.where(use, np.rint(kk / width).astype(int), -1) if len(cells) > 1 else np.where(use, np.arange(kk.size), -1)
    _, shell[use] = np.unique(shell[use], return_inverse=True)
    n = np.bincount(shell[use])
    return shell, np.bincount(shell[use], kk[use]) / n


def binned(values: np.ndarray, shell: np.ndarray) -> np.ndarray:
    """The mean of ``values`` over each shell of :func:`radial_bins`."""
    use = shell >= 0
    return np.bincount(shell[use], values[use]) / np.bincount(shell[use])


def draw_structure_factor(path: Path, scene, row: dict, steps) -> Path:
    """Draw ``row["structure_factor"]`` against |k| with the exact answer (if any) into ``path``."""
    cells, lengths = scene.grid.cells, scene.grid.lengths
    S, n = np.asarray(row["structure_factor"]), int(row["n_samples"])
    exact, label = exact_structure_factor(scene, steps)
    shell, k = radial_bins(cells, lengths)
    ref = exact if exact is not None else S
    rel = spectra.relative_se(cells, max(n, 1))
    use = shell >= 0  # the SE of a shell's mean: its modes' errors are independent
    se = np.sqrt(np.bincount(shell[use], (ref[use] * rel[use]) ** 2)) / np.bincount(shell[use])
    fig = Figure(figsize=(8, 6.5), dpi=DPI)
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    est = binned(S, shell)
    top.errorbar(k, est, yerr=se, fmt=".", ms=4, lw=0.8, color="C0", label=f"{scene.method.name} (±1 SE)")
    if exact is not None:
        top.plot(k, binned(exact, shell), color="0.4", lw=2.5, alpha=0.7, label=label)
        bottom.plot(k, (est - binned(exact, shell)) / se, ".", ms=4, color="C0")
        bottom.axhline(0, color="0.4", lw=1)
        bottom.axhspan(-2, 2, color="0.85", lw=0)
    top.axhline(1, color="C3", lw=0.8, ls=":", label="S = 1 (independent particles)")
    how = "" if len(cells) == 1 else ", binned by |k|"
    pooled = "samples pooled after t_equil" if scene.stats.t_equil is not None else "members"
    top.set(ylabel="S(k)", title=f"{scene.name}: {scene.method.name}, {n:,} {pooled}, "
            f"{'×'.join(map(str, cells))} cells{how}     {time_label(scene.n_steps * scene.dt)}    "
            f"S(0) = {S.flat[0]:.3g}")
    top.title.set_fontsize(9)
    top.legend(fontsize=8, loc="best")
    top.grid(alpha=0.3)
    bottom.set(xlabel="|k| [1/L]", ylabel="(est − exact)/SE")
    bottom.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
