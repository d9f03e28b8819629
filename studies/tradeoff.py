"""``python -m studies.tradeoff``: what accuracy each setting buys, and at what cost.

A user of :func:`ti_dk.tradeoff` (``python -m ti_dk.tradeoff``) on two of the paper's scenes: it
sweeps method, hybrid threshold, buffer width, C (Δt), precision, ghost profile and sub-steps on
``void1d`` (an ensemble pilot over the scene's output times up to ``--t-end``) and on a reduced
``ellipse2d`` (an ensemble of ``--ellipse-members`` members to its third output time). For each
setting the tool measures the bias of every per-cell moment (mean, variance, skewness, kurtosis)
against the particle method run beside it, over the low-density cells, with standard errors from
both ensembles; the error is the worst moment's noise-free RMS bias in standard errors of a run of
``--planned`` members (``ti_dk.core.bias``), and the cost the stepping time scaled to that run.
So both panels judge a bias against an ensemble's sampling error, never one member's χ².
Writes ``OUT/<scene>/`` (the tool's table, HDF5, PNG), ``OUT/tradeoff.png`` (both panels),
``OUT/tradeoff.h5`` and a Markdown table ``OUT/tradeoff.md``.
"""
import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

import ti_dk
from ti_dk.control.tradeoff import Candidate
from ti_dk.output.tradeoff import table

ELLIPSE_OUTPUT = 2  # ellipse2d's output time scored by default: its third, t = 0.00096 (the README's frame)


@dataclass
class Setting:
    label: str
    overrides: dict = field(default_factory=dict)
def void_settings() -> list[Setting]:
    s = [Setting("particle", {"method": "particle"}), Setting("fv", {"method": "fv"}),
         Setting("gaussian", {"method": "gaussian"}),
         Setting("hybrid fixed region (paper)", {"method": "hybrid", "regrid_interval": 0})]
    s += [Setting(f"hybrid threshold {t:g}", {"method": "hybrid", "threshold": t, "regrid_interval": 10})
          for t in (1, 2, 5, 10, 20)]
    s += [Setting(f"hybrid buffer {b}", {"method": "hybrid", "threshold": 5.0, "buffer": b, "regrid_interval": 10})
          for b in (0, 2, 4)]
    s += [Setting(f"{m} C={c:g}", {"method": m, "C": c, **({"regrid_interval": 0} if m == "hybrid" else {})})
          for m in ("fv", "hybrid") for c in (0.02, 0.125, 0.2)]
    s += [Setting(f"{m} f32", {"method": m, "precision": "f32", **({"regrid_interval": 0} if m == "hybrid" else {})})
          for m in ("fv", "hybrid")]
    s += [Setting(f"hybrid {g} ghosts{' (paper)' if g == 'uniform' else ''}",
                  {"method": "hybrid", "regrid_interval": 0, "ghost_profile": g}) for g in ("uniform", "linear")]
    s += [Setting(f"hybrid C=0.2 sub-steps {k}", {"method": "hybrid", "C": 0.2, "regrid_interval": 0,
                                                  "particle_substeps": k}) for k in (2, 4)]
    return s


def ellipse_settings() -> list[Setting]:
    s = [Setting("fv", {"method": "fv"}), Setting("gaussian", {"method": "gaussian"}),
         Setting("particle", {"method": "particle"})]
    s += [Setting(f"hybrid threshold {t:g}", {"method": "hybrid", "threshold": t}) for t in (1, 2, 5, 10, 20)]
    return s + [Setting("hybrid region_from member", {"method": "hybrid", "region_from": "member"})]


def sweep(scene_name: str, settings: list[Setting], base: dict, members: int, planned: int, out: Path,
          progress: bool = True) -> list[dict]:
    """:func:`ti_dk.tradeoff` of ``settings`` (the particles are its reference) on the scene with ``base``."""
    tries = [Candidate(s.label, s.overrides) for s in settings if s.label != "particle"]
    res = ti_dk.tradeoff(ti_dk.load_scene(scene_name, **base), planned=planned, tries=tries, defaults=False,
                         pilot_ensemble=members, progress=progress, out=out / scene_name)
    print(res.report(), file=sys.stderr)
    return [{k: v for k, v in r.items() if k in ("label", "cost", "wall", "error", "pareto", "negative_cells")}
            | {"summaries": r["summaries"]} for r in res.rows]


def criterion(rows: list[dict], tolerance: float = 1.5) -> float | None:
    """The smallest hybrid threshold whose error is within ``tolerance`` standard errors."""
    ok = [float(r["label"].split()[-1]) for r in rows
          if r["label"].startswith("hybrid threshold") and r["error"][0] <= tolerance]
    return min(ok) if ok else None


def plot(results: dict[str, list[dict]], out: Path) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(7 * len(results), 5.5))
    for ax, (name, rows) in zip(np.atleast_1d(axes), results.items()):
        cost = np.array([r["cost"] for r in rows])
        err = np.array([r["error"] for r in rows])
        front = np.array([r["pareto"] for r in rows])
        ax.errorbar(cost, err[:, 0], yerr=[err[:, 0] - err[:, 1], err[:, 2] - err[:, 0]], fmt="none", ecolor="0.6")
        ax.scatter(cost[~front], err[~front, 0], c="0.5", s=25)
        order = np.argsort(cost[front])
        ax.plot(cost[front][order], err[front][order, 0], "o-", c="C3", label="Pareto front")
        for r, c, e in zip(rows, cost, err[:, 0]):
            ax.annotate(r["label"], (c, e), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set(xscale="log", xlabel="cost of the planned run [s]", title=name,
               ylabel="error: worst moment's RMS bias over low-density cells, in SEs of the planned run")
        ax.set_yscale("symlog", linthresh=0.1)
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.axhline(1.0, color="k", lw=0.8, ls=":")
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "tradeoff.png", dpi=110)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.tradeoff", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--ensemble", type=int, default=2000, help="void1d pilot members")
    p.add_argument("--t-end", type=float, default=0.0025, help="void1d end time")
    p.add_argument("--planned", type=int, default=20000, help="the planned ensemble errors are measured at")
    p.add_argument("--cells", type=int, default=64, help="ellipse2d cells per axis")
    p.add_argument("--ellipse-members", type=int, default=16, help="ellipse2d pilot members")
    p.add_argument("--ellipse-t-end", type=float,
                   default=ti_dk.load_scene("ellipse2d").stats.output_times[ELLIPSE_OUTPUT], help=f"ellipse2d end time: the scene's output time number {ELLIPSE_OUTPUT + 1}")
    p.add_argument("--only", nargs="+", metavar="SETTING", help="run only these settings (labels as in the table)")
    p.add_argument("--out", default="renders/tradeoff")
    args = p.parse_args(argv)
    out = Path(args.out)
    void_s, ell_s = void_settings(), ellipse_settings()
    if args.only:
        known = {s.label for s in void_s + ell_s}
        if unknown := [x for x in args.only if x not in known]:
            print(f"ti_dk: error: --only {unknown[0]!r}: no such setting; use labels from "
                  f"{', '.join(sorted(known))}", file=sys.stderr)
            return 2
        void_s, ell_s = ([s for s in ss if s.label in args.only] for ss in (void_s, ell_s))
    ti_dk.init("cpu")
    out.mkdir(parents=True, exist_ok=True)
    times = [t for t in ti_dk.load_scene("void1d").stats.output_times if t < args.t_end] + [args.t_end]
    base = {"t_end": args.t_end, "output_times": times}
    t_ell = args.ellipse_t_end
    ell_base = {"cells": [args.cells, args.cells], "compare": "none", "t_end": t_ell, "output_times": [t_ell]}
    try:
        void = sweep("void1d", void_s, base, args.ensemble, args.planned, out)
        ell = sweep("ellipse2d", ell_s, ell_base, args.ellipse_members, args.planned, out)
    except (ti_dk.ConfigError, ti_dk.SimulationError) as exc:
        print(f"ti_dk: error: {exc}", file=sys.stderr)
        return 2
    results = {f"void1d, pilot of {args.ensemble} members, t ≤ {args.t_end:g}": void,
               f"ellipse2d {args.cells}², pilot of {args.ellipse_members} members, t = {t_ell:g}": ell}
    plot(results, out)
    with h5py.File(out / "tradeoff.h5", "w") as f:
        for name, rows in (("void1d", void), ("ellipse2d", ell)):
            f.attrs[name] = json.dumps([{k: v for k, v in r.items() if k != "summaries"} for r in rows])
    crit = criterion(void)
    for rows in (void, ell):
        for r in rows:
            r["meets"], r["same_as"] = None, []
    text = (f"## void1d (pilot {args.ensemble} members, t ≤ {args.t_end:g}; errors in SEs of {args.planned:,} "
            f"members)\n\n```\n{table(void, 'z')}\n```\n"
            + f"\nSmallest hybrid threshold within 1.5 standard errors: {crit}\n\n"
            + f"## ellipse2d ({args.cells}², t = {t_ell:g}, pilot {args.ellipse_members} members)\n\n"
            + f"```\n{table(ell, 'z')}\n```\n")
    (out / "tradeoff.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
