"""A run's per-member series over time (:class:`ti_dk.control.handlers.Observations`): read back
from a result or a run file, drawn as the ensemble mean ± standard error (``series.png``: mass,
negative cells and, for the hybrid, the particles in its region and its cells;
``observables.png``: the scene's ``[observables]``), and the crossing rate between two
observables (:func:`crossing_rate`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

PANELS = {"mass": "mass [particles]", "negative_cells": "negative cells", "particles": "particles in the region",
          "region_cells": "cells of the particle region"}  # series.png, top to bottom (those a run has)


def read_series(source) -> dict[str, np.ndarray]:
    """``time`` ``(records,)`` and every per-member series and observable ``(records, members)`` of a
    :class:`ti_dk.Result` or a run file (its ``/series`` and ``/observables``)."""
    if hasattr(source, "series"):
        return dict(source.series)
    with h5py.File(source, "r") as f:
        return {k: g[k][()] for name in ("series", "observables") if name in f for g in (f[name],) for k in g}


def mean_se(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over members (the last axis) and its standard error (NaN for one member)."""
    v = np.asarray(values, dtype=np.float64)
    m = v.shape[-1]
    se = v.std(axis=-1, ddof=1) / math.sqrt(m) if m > 1 else np.full(v.shape[:-1], np.nan)
    return v.mean(axis=-1), se


def _band(ax, t: np.ndarray, values: np.ndarray, color: str, label: str) -> None:
    """The members' mean against t with a ±1 SE band (none for one member)."""
    mean, se = mean_se(values)
    ax.plot(t, mean, color=color, lw=1.2, label=label)
    if values.shape[-1] > 1:
        ax.fill_between(t, mean - se, mean + se, color=color, alpha=0.3, lw=0)


def _figure(rows: int) -> tuple:
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # matplotlib only when drawing
    from matplotlib.figure import Figure

    from .render import DPI

    fig = Figure(figsize=(8, 1.2 + 1.9 * rows), dpi=DPI)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    return fig, list(axes)


def _title(scene, members: int) -> str:
    how = f"mean ± SE over {members:,} members" if members > 1 else "one member"
    return f"{scene.name}: {scene.method.name}, {how}"


def _save(fig, axes: list, path: Path) -> Path:
    axes[-1].set_xlabel("t [L²/(2D)]")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def draw_series(path: Path, scene, series: dict[str, np.ndarray], diagnostics: dict | None = None) -> Path:
    """``series.png``: one panel per series of :data:`PANELS` the run has, mean ± SE over members;
    with a method run alongside (``scene.method.compare``), its mass and negative cells per member
    from the per-step ``diagnostics`` (sums over members) beside them."""
    keys = [k for k in PANELS if k in series]
    fig, axes = _figure(len(keys))
    members = series["mass"].shape[-1]
    for ax, k in zip(axes, keys):
        _band(ax, series["time"], series[k], "C0", scene.method.name)
        ax.set_ylabel(PANELS[k], fontsize=9)
        other = (diagnostics or {}).get(f"compare_{k}")
        if other is not None and len(other):
            ax.plot(diagnostics["time"], np.asarray(other) / members, color="C1", lw=1.0,
                    label=f"{scene.method.compare} (run alongside, every step)")
            ax.legend(fontsize=8, loc="best")
    axes[0].set_title(_title(scene, series["mass"].shape[-1]), fontsize=10)
    return _save(fig, axes, path)


def draw_observables(path: Path, scene, series: dict[str, np.ndarray]) -> Path:
    """``observables.png``: every observable's particle count, mean ± SE over members, on one axis
    (a log scale when their positive means span more than two decades; zeros are then left out)."""
    names = [name for name, _ in scene.stats.observables]
    fig, axes = _figure(1)
    ax = axes[0]
    for i, (name, text) in enumerate(scene.stats.observables):
        _band(ax, series["time"], series[name], f"C{i}", f"{name}: {text}")
    means = np.concatenate([mean_se(series[n])[0] for n in names])
    positive = means[means > 0]
    if positive.size and positive.max() / positive.min() > 100:  # a well and the leak into the other
        ax.set_yscale("log", nonpositive="mask")  # a count of 0 is left out
    ax.set_ylabel("particles in the region", fontsize=9)
    ax.set_title(_title(scene, series[names[0]].shape[-1]), fontsize=10)
    ax.legend(fontsize=8, loc="best")
    return _save(fig, axes, path)


def summary_lines(scene, series: dict[str, np.ndarray]) -> list[str]:
    """The observables at the last record, mean ± SE over members, for the run's summary."""
    names = [name for name, _ in scene.stats.observables]
    if not names or not len(series.get("time", ())):
        return []
    members = series[names[0]].shape[-1]
    parts = []
    for name in names:
        mean, se = mean_se(series[name][-1])
        parts.append(f"{name} {float(mean):,.6g}" + (f" ± {float(se):,.2g}" if members > 1 else ""))
    how = f"mean ± SE over {members:,} members" if members > 1 else "one member"
    return [f"observables at t = {series['time'][-1]:.4g} (particles, {how}): " + ", ".join(parts)]


@dataclass(frozen=True)
class Rate:
    """A crossing rate: the members' mean, its standard error (NaN for one member), the members."""

    value: float
    se: float
    members: int

    def __str__(self) -> str:
        if self.members < 2:
            return f"{self.value:.4g} per L²/(2D) (one member: no standard error)"
        return f"{self.value:.4g} ± {self.se:.2g} per L²/(2D) ({self.members} members)"


def two_state_rate(t: np.ndarray, f: np.ndarray, t_from: float = 0.0) -> np.ndarray:
    """The rate k of the symmetric two-state model, ``f(t) = (1 − e^{−2kt})/2``: the least-squares
    slope of ``−ln(1 − 2f)/2`` against t on ``t ≥ t_from``, for each row of ``f`` (time last)."""
    keep = np.asarray(t) >= t_from - 1e-12
    if keep.sum() < 2:
        raise ValueError(f"t_from = {t_from:g} leaves {keep.sum()} record(s): give an earlier t_from")
    with np.errstate(invalid="ignore", divide="ignore"):
        y = -np.log(1 - 2 * np.asarray(f, dtype=np.float64)[..., keep]) / 2
    return np.polyfit(np.asarray(t)[keep], y.T, 1)[0]


def crossing_rate(source, start: str = "left", end: str = "right", t_from: float = 0.0) -> Rate:
    r"""The rate at which particles cross from observable ``start`` into ``end`` (e.g. the two wells
    of ``doublewell2d``), with its standard error over the members.

    For each member, ``f(t) = N_end / (N_start + N_end)`` from the records (every ``sample_every``
    steps) and the symmetric two-state model's rate :func:`two_state_rate` on ``t ≥ t_from``
    (``k = slope`` of ``−ln(1 − 2f)/2``, the one-way rate while ``f ≪ ½``; start after the
    blob has relaxed in its well). The members' mean and standard error.

    Parameters
    ----------
    source : ti_dk.Result or str or pathlib.Path
        A run's result, or its run file (``/observables``).
    start, end : str
        The observables' names (``[observables]`` of the scene).
    t_from : float
        The first time of the fit [L²/(2D)].

    Returns
    -------
    Rate
        ``value`` [1 / (L²/(2D))], ``se`` (NaN for one member), ``members``.
    """
    series = read_series(source)
    missing = [name for name in (start, end) if name not in series]
    if missing:
        have = [k for k in series if k not in ("time", *PANELS)]
        raise ValueError(f"the run has no observable {missing[0]!r}: it has {', '.join(have) or 'none'}; "
                         "add it to [observables]")
    a, b = (np.asarray(series[k], dtype=np.float64).T for k in (start, end))  # (members, records)
    k = two_state_rate(series["time"], b / (a + b), t_from)
    mean, se = mean_se(k)
    return Rate(float(mean), float(se), k.size)
