"""``python -m studies.figures fig2|fig3|fig4``: the paper's statistics figures from our own runs.

Each command runs its scenes through :func:`ti_dk.run` into ``OUT/runs/<tag>/<scene>_<method>.h5``
(a complete file for the same scene is read instead of run again), draws from those files, and
writes ``OUT/<fig>.png`` and the data drawn, ``OUT/<fig>.h5``, with the exact particle answer
beside the methods: the binomial distribution at equilibrium (Figs. 2–3), the Poisson-binomial
distribution for the void (Fig. 4). Sizes (cells, lengths, output times) are the scene's, so
``--set`` changes them for every run and for the exact answer alike.
"""
import argparse
import math
import sys
import time
from pathlib import Path

import h5py
import numpy as np

import ti_dk
from ti_dk.core import theory

from .runs import Run, Runs, parse_sets

METHODS = ("particle", "fv", "gaussian")
STYLE = {"particle": dict(color="k", marker="o", ls="none", ms=3), "fv": dict(color="C0"),
         "gaussian": dict(color="C1", ls="--"), "hybrid": dict(color="C3"), "exact": dict(color="0.5", lw=3, alpha=0.6)}


def equilibrium(runs: Runs, tag: str, method: str, ppc: float, ensemble: int, seed: int = 1, **over) -> Run:
    """Stationary statistics of ``ppc`` particles per cell in the ``equilibrium1d`` scene (pooled in time).

    Particles start from the exact equilibrium (N uniform particles) and are pooled from t = 0;
    the SPDEs start uniform and are pooled after ``t_equil`` of the scene."""
    kw = dict(method=method, ppc=ppc, ensemble=ensemble, seed=seed, histogram=[-10, int(2 * ppc + 12)])
    if method == "particle":
        kw |= dict(particle_init="exact_uniform", t_equil=0.0, t_end=0.01)
    return runs.get(tag, "equilibrium1d", **kw | over)


def _binomial_pmf(scene: ti_dk.Scene) -> np.ndarray:
    """The count in one cell of N uniform particles in M cells: Binomial(N, 1/M)."""
    cells, total = math.prod(scene.grid.cells), round(scene.initial_ppc.sum())
    return theory.poisson_binomial_pmf(np.array([1 / cells]), np.array([total]))


def fig2(ensemble: int, out: Path, plt, runs: Runs | None = None) -> dict:
    """Equilibrium PDFs of particles per cell at 5 and 1 particles per cell."""
    runs = runs or Runs(out / "runs")
    data = {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, ppc in zip(axes, (5, 1)):
        for m in METHODS:
            res = equilibrium(runs, f"fig2_ppc{ppc}", m, ppc, ensemble)
            h = res.stats.histogram[-1].sum(axis=0)  # pooled over cells
            k = res.stats.hist_lo + np.arange(h.size)
            pdf = h / h.sum()
            data[f"ppc{ppc}/{m}"] = np.stack([k, pdf])
            ax.plot(k, pdf, label=m, **STYLE[m])
        exact = _binomial_pmf(res.scene)
        data[f"ppc{ppc}/exact"] = np.stack([np.arange(exact.size), exact])
        ax.plot(np.arange(exact.size), exact, label="exact (binomial)", **STYLE["exact"])
        ax.set(title=f"{ppc} particle{'s' * (ppc != 1)} per cell", xlabel="particles in a cell (bins one particle wide)",
               ylabel="probability", xlim=(-4, 4 * ppc + 6))
        ax.legend()
    return _save(fig, out, "fig2", data)


PPCS = (1, 2, 5, 10, 20, 50, 100)


def fig3(ensemble: int, out: Path, plt, ppcs: tuple[float, ...] = PPCS, runs: Runs | None = None) -> dict:
    """Skewness and kurtosis against particles per cell; error bars: spread over the cells."""
    runs = runs or Runs(out / "runs")
    data = {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for m in METHODS:
        rows = []
        for ppc in ppcs:
            res = equilibrium(runs, f"fig3_ppc{ppc:g}", m, ppc, ensemble, histogram=None)
            s, k = res.stats.skewness[-1].ravel(), res.stats.kurtosis[-1].ravel()
            n = s.size
            rows.append((ppc, s.mean(), s.std(ddof=1) / math.sqrt(n), k.mean(), k.std(ddof=1) / math.sqrt(n)))
        r = np.array(rows)
        data[m] = r
        axes[0].errorbar(r[:, 0], r[:, 1], yerr=r[:, 2], label=m, capsize=3, **STYLE[m])
        axes[1].errorbar(r[:, 0], r[:, 3], yerr=r[:, 4], label=m, capsize=3, **STYLE[m])
    cells = math.prod(res.scene.grid.cells)
    ppc = np.geomspace(1, 100, 60)
    exact = np.array([[theory.binomial_moments(int(round(cells * p)), 1 / cells)[k] for k in ("skewness", "kurtosis")]
                      for p in ppc])
    data["exact"] = np.column_stack([ppc, exact])
    for ax, col, name in ((axes[0], 0, "skewness"), (axes[1], 1, "kurtosis")):
        ax.plot(ppc, exact[:, col], label="exact (binomial)", **STYLE["exact"])
        ax.set(xscale="log", xlabel="particles per cell", ylabel=name, title=f"{name} at equilibrium")
        ax.legend()
    return _save(fig, out, "fig3", data)


def fig4(ensemble: int, out: Path, plt, runs: Runs | None = None) -> dict:
    """``void1d``: mean, variance, skewness and kurtosis profiles at the scene's last output time."""
    runs = runs or Runs(out / "runs", progress=sys.stderr.isatty())
    data = {}
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    results = {m: runs.get("fig4", "void1d", method=m, ensemble=ensemble) for m in (*METHODS, "hybrid")}
    scene = results["fv"].scene
    x = (np.arange(scene.grid.cells[0]) + 0.5) * scene.grid.dx[0]
    row = -1
    t = results["fv"].times[row]
    exact = theory.particle_counts_periodic(scene.initial_ppc, scene.grid.lengths, scene.dt, round(t / scene.dt))
    vol = scene.grid.cell_volume
    for m, res in results.items():
        st = res.stats
        prof = {"mean": st.mean[row] * vol, "variance": st.variance[row] * vol**2,
                "skewness": st.skewness[row], "kurtosis": st.kurtosis[row]}
        data[m] = np.stack([prof[k] for k in prof])
        data[f"{m}_wall_time"] = np.float64(res.wall_time)
        for ax, (k, v) in zip(axes.flat, prof.items()):
            ax.plot(x, v, label=m, **({"lw": 1} | STYLE[m]))
    data["exact"] = np.stack([exact[k] for k in ("mean", "variance", "skewness", "kurtosis")])
    for ax, k in zip(axes.flat, ("mean", "variance", "skewness", "kurtosis")):
        ax.plot(x, exact[k], label="exact (Poisson-binomial)", **STYLE["exact"])
        ax.set(xlabel="x", ylabel=f"{k} (particles per cell)" if k in ("mean", "variance") else k,
               title=f"{k}, t = {t:g}, {scene.method.ensemble} members")
    axes[0, 0].legend()
    axes[1, 1].set_ylim(0, 12)
    axes[1, 0].set_ylim(-1, 3)
    return _save(fig, out, "fig4", data)


def _save(fig, out: Path, name: str, data: dict) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=110)
    with h5py.File(out / f"{name}.h5", "w") as f:
        for k, v in data.items():
            f.create_dataset(k, data=v)
    return data


FIGURES = {"fig2": (fig2, 100), "fig3": (fig3, 100), "fig4": (fig4, 20000)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.figures", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("figure", choices=FIGURES)
    p.add_argument("--ensemble", type=int, help="members (default: 100 for fig2/fig3, 20000 for fig4)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key in every run, e.g. --set cells=[20]")
    p.add_argument("--rerun", action="store_true", help="run every scene again, even where its .h5 is there")
    p.add_argument("--out", default="renders/figures", help="output directory")
    p.add_argument("--arch", default="cpu")
    args = p.parse_args(argv)
    import matplotlib  # a core dependency (the frames use its colormap)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fn, default = FIGURES[args.figure]
    if args.ensemble is not None and args.ensemble < 2:
        print("ti_dk: error: --ensemble needs at least 2 members", file=sys.stderr)
        return 2
    out = Path(args.out)
    t0 = time.perf_counter()
    try:
        runs = Runs(out / "runs", parse_sets(args.set), args.rerun, progress=sys.stderr.isatty())
        ti_dk.init(args.arch)
        fn(args.ensemble or default, out, plt, runs=runs)
    except (ti_dk.ConfigError, ti_dk.SimulationError) as exc:
        print(f"ti_dk: error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.figure}: wrote {out / args.figure}.png and .h5 in {time.perf_counter() - t0:.1f} s "
          f"(runs in {out / 'runs'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
