"""What the speed/accuracy pilot (:mod:`ti_dk.control.tradeoff`) writes: its table as text, CSV and
HDF5, the PNG of cost against error with the Pareto front, and the picked setting as a scene file."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import numpy as np

from ..core.bias import MOMENTS, SUMMARIES

SHORT = {"mean": "mean", "variance": "var", "skewness": "skew", "kurtosis": "kurt"}


def columns(row: dict) -> dict:
    """One candidate's row as flat columns (CSV and HDF5): every summary with its one-SE band."""
    out = {"setting": row["label"], "overrides": json.dumps(row["overrides"]), "cost_s": row["cost"],
           "pilot_wall_s": row["wall"], "error": row["error"][0], "error_low": row["error"][1],
           "error_high": row["error"][2], "pareto": row["pareto"], "meets": row["meets"], "sure": row.get("sure", True),
           "negative_cells": row["negative_cells"], "indistinguishable_from": "; ".join(row["same_as"])}
    for k in MOMENTS:
        for s in SUMMARIES:
            v, lo, hi = row["summaries"][k, s]
            out |= {f"{k}_{s}": v, f"{k}_{s}_low": lo, f"{k}_{s}_high": hi}
    return out


def table(rows: list[dict], measure: str) -> str:
    """The printed table: cost at the planned ensemble, each moment's error (``measure``: ``z`` in
    SEs at the planned ensemble, ``rel`` relative) with its band, the worst, Pareto ★, meets (``?``:
    the band spans the target, the pilot cannot tell)."""
    head = ["setting", "cost [s]"] + [SHORT[k] for k in MOMENTS] + ["error", "front", "meets"]
    lines = []
    for r in rows:
        cells = [r["label"], f"{r['cost']:.3g}"]
        cells += [_band(r["summaries"][k, measure], measure) for k in MOMENTS]
        meets = {True: "yes", False: "no", None: ""}[r["meets"]] + ("" if r.get("sure", True) else "?")
        cells += [_band(r["error"], measure), "★" if r["pareto"] else "", meets]
        lines.append(cells)
    widths = [max(len(str(c)) for c in col) for col in zip(head, *lines)]
    fmt = "  ".join(f"{{:{'<' if i == 0 else '>'}{w}}}" for i, w in enumerate(widths))
    return "\n".join(fmt.format(*line) for line in [head, *lines])


def _band(v: tuple[float, float, float], measure: str) -> str:
    f = (lambda x: f"{100 * x:.2g}%") if measure == "rel" else (lambda x: f"{x:.3g}")
    return f"{f(v[0])} [{f(v[1])}–{f(v[2])}]"


def write_csv(path: Path, rows: list[dict]) -> None:
    """The pilot's table at ``path`` as CSV, one line per setting (:func:`columns`)."""
    cols = [columns(r) for r in rows]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(cols[0]))
        w.writeheader()
        w.writerows(cols)


def write_h5(path: Path, rows: list[dict], attrs: dict, cell_maps: dict[str, dict[str, np.ndarray]],
             mask: np.ndarray) -> None:
    """``/table/<column>`` (one entry per setting), ``/cells/<setting>/<moment>_bias`` and
    ``_se`` (per row and cell, particles per cell for the mean), ``/mask`` (the cells scored) and the
    pilot's facts as attributes."""
    cols = [columns(r) for r in rows]
    with h5py.File(path, "w") as f:
        for k, v in attrs.items():
            f.attrs[k] = v
        t = f.create_group("table")
        for name in cols[0]:
            values = [c[name] for c in cols]
            t[name] = np.array(values, dtype=h5py.string_dtype()) if isinstance(values[0], str) else np.array(values,
                                                                                                            dtype=float)
        f["mask"] = mask
        for label, maps in cell_maps.items():
            g = f.create_group(f"cells/{label.replace('/', '_')}")
            for k, v in maps.items():
                g[k] = v


def plot(path: Path, rows: list[dict], title: str, ylabel: str, target: float | None, pick: str | None) -> None:
    """Cost against error, each with its one-SE band, the Pareto front joined, the target dashed and
    the pick ringed; errors of 0 sit on the symlog axis's 0."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    cost = np.array([r["cost"] for r in rows])
    err = np.array([r["error"] for r in rows])  # value, low, high
    front = np.array([r["pareto"] for r in rows])
    ax.errorbar(cost, err[:, 0], yerr=[err[:, 0] - err[:, 1], err[:, 2] - err[:, 0]], fmt="none", ecolor="0.6", lw=1)
    ax.scatter(cost[~front], err[~front, 0], c="0.45", s=25, zorder=3, label="dominated")
    order = np.argsort(cost[front])
    ax.plot(cost[front][order], err[front][order, 0], "o-", c="C3", zorder=4, label="Pareto front")
    if target is not None:
        ax.axhline(target, color="k", lw=0.9, ls="--", label=f"target {target:g}")
    if pick is not None:
        i = [r["label"] for r in rows].index(pick)
        ax.scatter(cost[i], err[i, 0], s=220, facecolors="none", edgecolors="C2", lw=2, zorder=5, label=f"pick: {pick}")
    linthresh = max(target or 0.0, 1e-3) / 10 if target else max(np.nanmax(err[:, 2]), 1e-3) / 100
    ax.set(xscale="log", xlabel="cost at the planned ensemble, full horizon [s, this machine]", ylabel=ylabel,
           title=title)
    ax.set_yscale("symlog", linthresh=linthresh)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    _labels(fig, ax, [r["label"] for r in rows], cost, err[:, 0])
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _labels(fig, ax, names: list[str], x: np.ndarray, y: np.ndarray) -> None:
    """Each point's name beside it, moved up a line at a time until it overlaps no name placed
    before it (settings of about the same cost and error would otherwise print over each other)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    placed = []
    for i in np.lexsort((x, y)):
        text = ax.annotate(names[i], (x[i], y[i]), fontsize=7, xytext=(4, 3), textcoords="offset points")
        box = text.get_window_extent(renderer)
        for lift in range(1, 12):
            if not any(box.overlaps(b) for b in placed):
                break
            text.xyann = (4, 3 + 8 * lift)
            box = text.get_window_extent(renderer)
        placed.append(box)


def scene_toml(scene, comment: str) -> str:
    """The scene as a complete TOML scene file (``Scene.to_dict``; keys without a value left out)."""
    d = scene.to_dict()
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [f"{k} = {_value(v)}" for k, v in d.items() if not isinstance(v, dict) and v is not None]
    for table_name, kv in d.items():
        if isinstance(kv, dict):
            lines += ["", f"[{table_name}]"] + [f"{k} = {_value(v)}" for k, v in kv.items() if v is not None]
    return "\n".join(lines) + "\n"


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string is a JSON string
    if isinstance(v, float):
        return repr(v) if np.isfinite(v) else ("inf" if v > 0 else "-inf") if np.isinf(v) else "nan"
    return str(v)
