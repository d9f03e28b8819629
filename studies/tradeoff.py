"""``python -m studies.tradeoff``: what accuracy each setting buys, and at what cost.

Sweeps method, hybrid threshold, buffer width, C (Δt) and precision on ``void1d`` (an ensemble,
against the exact Poisson-binomial particle answer) and on a reduced ``ellipse2d`` (one member,
against the exact particle mean and variance of every cell). For each setting it records the
wall time, the error, the negative cells, and marks the Pareto front (no other setting is both
faster and more accurate). Each setting is run through :func:`ti_dk.run` into
``OUT/runs/<scene>/<setting>/<scene>_<method>.h5`` (a complete file for the same scene is read
instead of run again; its wall time is the one recorded) and scored from that file. Writes
``OUT/tradeoff.png``, ``OUT/tradeoff.h5`` and a Markdown table.

Error on ``void1d``, for each statistic k of the per-cell counts (mean, variance, skewness,
kurtosis) over the low-density cells L (exact mean between 0.5 and 10 particles):

    e_k = sqrt( mean_{i∈L} z_{k,i}² ),   z_{k,i} = (estimate − exact) / sampling SE,

so e_k ≈ 1 is "exact within sampling error"; the headline error is max_k e_k. Error on
``ellipse2d``: χ² per cell of the single realisation against the exact particle mean and variance,
mean_i (q_i − m_i)² / v_i, which is 1 for a correct realisation; the error is |χ² − 1|.
"""
import argparse
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

import ti_dk
from ti_dk.core import theory

from .runs import Run, Runs

KEYS = ("mean", "variance", "skewness", "kurtosis")
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
    return s + [Setting("hybrid regrid_floor 0", {"method": "hybrid", "regrid_floor": 0.0})]


def void_error(res: Run | ti_dk.Result) -> dict[str, float]:
    """Per-moment RMS z over the low-density cells at the last output time, and their worst."""
    sc, t = res.scene, res.times[-1]
    k = sc.hybrid.particle_substeps if sc.method.name == "hybrid" else 1  # the particles' own step is Δt/k
    ppc0, dt, steps = sc.initial_ppc, sc.dt / k, round(t / sc.dt) * k
    mean = theory.particle_counts_periodic(ppc0, sc.grid.lengths, dt, steps)["mean"]
    cells = (mean > 0.5) & (mean < 10)
    exact, se = theory.void_reference(ppc0, sc.grid.lengths[0], dt, steps, sc.method.ensemble, cells, replicas=100)
    vol = res.cell_volume
    est = {"mean": res.stats.mean[-1] * vol, "variance": res.stats.variance[-1] * vol**2,
           "skewness": res.stats.skewness[-1], "kurtosis": res.stats.kurtosis[-1]}
    err = {k: float(np.sqrt(np.nanmean(((est[k] - exact[k]) / se[k])[cells] ** 2))) for k in KEYS}
    err["error"] = max(err.values())
    return err


def ellipse_error(res: Run | ti_dk.Result) -> dict[str, float]:
    """χ² per cell of a one-member run's last row against the exact particle mean and variance."""
    sc, t = res.scene, res.times[-1]
    exact = theory.particle_counts_periodic(sc.initial_ppc, sc.grid.lengths, sc.dt, round(t / sc.dt))
    q = res.stats.mean[-1] * sc.grid.cell_volume  # one member: the mean is its density
    chi2 = float(np.mean((q - exact["mean"]) ** 2 / exact["variance"]))
    return {"chi2": chi2, "error": abs(chi2 - 1.0)}


def pareto(cost: np.ndarray, err: np.ndarray) -> np.ndarray:
    """True for settings no other setting beats in both cost and error."""
    return np.array([not np.any((cost <= c) & (err <= e) & ((cost < c) | (err < e))) for c, e in zip(cost, err)])


def sweep(runs: Runs, scene_name: str, settings: list[Setting], base: dict, error, progress=True) -> list[dict]:
    rows = []
    for s in settings:
        tag = re.sub(r"[^\w.=-]+", "_", s.label)  # the label as a directory name
        res = runs.get(f"{scene_name}/{tag}", scene_name, **base | s.overrides)
        wall = res.wall_time
        row = {"setting": s.label, "wall_time": wall, "negative_cells": int(res.diagnostics["negative_cells"].max()),
               **error(res)}
        rows.append(row)
        if progress:
            print(f"  {scene_name}: {s.label:32s} {wall:7.2f} s  error {row['error']:8.2f}", file=sys.stderr)
    cost = np.array([r["wall_time"] for r in rows])
    err = np.array([r["error"] for r in rows])
    for r, p in zip(rows, pareto(cost, err)):
        r["pareto"] = bool(p)
    return rows


def criterion(rows: list[dict], tolerance: float = 1.5) -> float | None:
    """The smallest hybrid threshold whose error is within ``tolerance`` sampling errors."""
    ok = [float(r["setting"].split()[-1]) for r in rows
          if r["setting"].startswith("hybrid threshold") and r["error"] <= tolerance]
    return min(ok) if ok else None


def table(rows: list[dict], keys: tuple[str, ...]) -> str:
    head = "| setting | wall s | " + " | ".join(keys) + " | negative cells | Pareto |\n"
    head += "|---" * (len(keys) + 4) + "|\n"
    return head + "".join(
        f"| {r['setting']} | {r['wall_time']:.2f} | " + " | ".join(f"{r[k]:.2f}" for k in keys)
        + f" | {r['negative_cells']} | {'★' if r['pareto'] else ''} |\n" for r in rows)


def plot(results: dict[str, list[dict]], out: Path) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(7 * len(results), 5.5))
    for ax, (name, rows) in zip(np.atleast_1d(axes), results.items()):
        cost = np.array([r["wall_time"] for r in rows])
        err = np.array([r["error"] for r in rows])
        front = np.array([r["pareto"] for r in rows])
        ax.scatter(cost[~front], err[~front], c="0.5", s=25)
        order = np.argsort(cost[front])
        ax.plot(cost[front][order], err[front][order], "o-", c="C3", label="Pareto front")
        for r, c, e in zip(rows, cost, err):
            ax.annotate(r["setting"], (c, e), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set(xscale="log", yscale="log", xlabel="wall time [s]", title=name,
               ylabel="error (RMS z over low-density cells, worst moment; 1 = exact)" if "void" in name
               else "|χ² per cell − 1| against the exact particle answer")
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        if "void" in name:
            ax.axhline(1.0, color="k", lw=0.8, ls=":")
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "tradeoff.png", dpi=110)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.tradeoff", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--ensemble", type=int, default=2000, help="void1d members")
    p.add_argument("--t-end", type=float, default=0.0025, help="void1d end time")
    p.add_argument("--cells", type=int, default=64, help="ellipse2d cells per axis")
    p.add_argument("--ellipse-t-end", type=float, default=ti_dk.load_scene("ellipse2d").stats.output_times[ELLIPSE_OUTPUT],
                   help=f"ellipse2d end time: the scene's output time number {ELLIPSE_OUTPUT + 1}")
    p.add_argument("--only", nargs="+", metavar="SETTING", help="run only these settings (labels as in the table)")
    p.add_argument("--rerun", action="store_true", help="run every setting again, even where its .h5 is there")
    p.add_argument("--out", default="renders/tradeoff")
    args = p.parse_args(argv)
    out = Path(args.out)
    runs = Runs(out / "runs", rerun=args.rerun)
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
    base = {"ensemble": args.ensemble, "t_end": args.t_end, "output_times": [args.t_end]}
    t_ell = args.ellipse_t_end
    ell_base = {"cells": [args.cells, args.cells], "compare": "none", "t_end": t_ell, "output_times": [t_ell]}
    try:
        void = sweep(runs, "void1d", void_s, base, void_error)
        ell = sweep(runs, "ellipse2d", ell_s, ell_base, ellipse_error)
    except (ti_dk.ConfigError, ti_dk.SimulationError) as exc:
        print(f"ti_dk: error: {exc}", file=sys.stderr)
        return 2
    results = {f"void1d, {args.ensemble} members, t = {args.t_end:g}": void,
               f"ellipse2d {args.cells}², one member, t = {t_ell:g}": ell}
    plot({k: v for k, v in results.items() if v}, out)
    with h5py.File(out / "tradeoff.h5", "w") as f:
        for name, rows in (("void1d", void), ("ellipse2d", ell)):
            f.attrs[name] = json.dumps(rows)
    crit = criterion(void)
    text = (f"## void1d ({args.ensemble} members, t = {args.t_end:g})\n\n" + table(void, (*KEYS, "error"))
            + f"\nSmallest hybrid threshold within 1.5 sampling errors: {crit}\n\n"
            + f"## ellipse2d ({args.cells}², t = {t_ell:g})\n\n" + table(ell, ("chi2", "error")))
    (out / "tradeoff.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
