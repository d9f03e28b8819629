"""``python -m ti_dk.figures fig2|fig3|fig4``: the paper's statistics figures from our own runs.

Each command writes ``OUT/<fig>.png`` and the data behind it, ``OUT/<fig>.h5``, and draws the
exact particle answer beside the methods: the binomial distribution at equilibrium (Figs. 2–3),
the Poisson-binomial distribution for the void (Fig. 4).
"""
import argparse
import math
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from . import config, sim, theory

METHODS = ("particle", "fv", "gaussian")
STYLE = {"particle": dict(color="k", marker="o", ls="none", ms=3), "fv": dict(color="C0"),
         "gaussian": dict(color="C1", ls="--"), "hybrid": dict(color="C3"), "exact": dict(color="0.5", lw=3, alpha=0.6)}


def equilibrium(method: str, ppc: float, ensemble: int, seed: int = 1, **over) -> sim.Result:
    """Stationary statistics of ``ppc`` particles per cell in 100 periodic cells (pooled in time).

    Particles start from the exact equilibrium (N uniform particles) and are pooled from t = 0;
    the SPDEs start uniform and are pooled after ``t_equil`` of the scene."""
    kw = dict(method=method, ppc=ppc, ensemble=ensemble, seed=seed, histogram=[-10, int(2 * ppc + 12)])
    if method == "particle":
        kw |= dict(particle_init="exact_uniform", t_equil=0.0, t_end=0.01)
    return sim.run(config.load_scene("equilibrium1d", **kw | over), progress=False)


def _binomial_pmf(ppc: float, cells: int = 100) -> np.ndarray:
    return theory.poisson_binomial_pmf(np.array([1 / cells]), np.array([int(round(ppc * cells))]))


def fig2(ensemble: int, out: Path, plt) -> dict:
    """Equilibrium PDFs of particles per cell at 5 and 1 particles per cell."""
    data = {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, ppc in zip(axes, (5, 1)):
        for m in METHODS:
            res = equilibrium(m, ppc, ensemble)
            h = res.stats.histogram[-1].sum(axis=0)  # pooled over cells
            k = res.stats.hist_lo + np.arange(h.size)
            pdf = h / h.sum()
            data[f"ppc{ppc}/{m}"] = np.stack([k, pdf])
            ax.plot(k, pdf, label=m, **STYLE[m])
        exact = _binomial_pmf(ppc)
        data[f"ppc{ppc}/exact"] = np.stack([np.arange(exact.size), exact])
        ax.plot(np.arange(exact.size), exact, label="exact (binomial)", **STYLE["exact"])
        ax.set(title=f"{ppc} particle{'s' * (ppc != 1)} per cell", xlabel="particles in a cell (bins one particle wide)",
               ylabel="probability", xlim=(-4, 4 * ppc + 6))
        ax.legend()
    return _save(fig, out, "fig2", data)


PPCS = (1, 2, 5, 10, 20, 50, 100)


def fig3(ensemble: int, out: Path, plt, ppcs: tuple[float, ...] = PPCS) -> dict:
    """Skewness and kurtosis against particles per cell; error bars: spread over the 100 cells."""
    data = {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for m in METHODS:
        rows = []
        for ppc in ppcs:
            res = equilibrium(m, ppc, ensemble, histogram=None)
            s, k = res.stats.skewness[-1], res.stats.kurtosis[-1]
            n = s.size
            rows.append((ppc, s.mean(), s.std(ddof=1) / math.sqrt(n), k.mean(), k.std(ddof=1) / math.sqrt(n)))
        r = np.array(rows)
        data[m] = r
        axes[0].errorbar(r[:, 0], r[:, 1], yerr=r[:, 2], label=m, capsize=3, **STYLE[m])
        axes[1].errorbar(r[:, 0], r[:, 3], yerr=r[:, 4], label=m, capsize=3, **STYLE[m])
    ppc = np.geomspace(1, 100, 60)
    exact = np.array([[theory.binomial_moments(int(round(100 * p)), 0.01)[k] for k in ("skewness", "kurtosis")]
                      for p in ppc])
    data["exact"] = np.column_stack([ppc, exact])
    for ax, col, name in ((axes[0], 0, "skewness"), (axes[1], 1, "kurtosis")):
        ax.plot(ppc, exact[:, col], label="exact (binomial)", **STYLE["exact"])
        ax.set(xscale="log", xlabel="particles per cell", ylabel=name, title=f"{name} at equilibrium")
        ax.legend()
    return _save(fig, out, "fig3", data)


def fig4(ensemble: int, out: Path, plt) -> dict:
    """``void1d``: mean, variance, skewness and kurtosis profiles at the scene's output times."""
    data = {}
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    results = {m: sim.run(config.load_scene("void1d", method=m, ensemble=ensemble), progress=sys.stderr.isatty())
               for m in (*METHODS, "hybrid")}
    scene = results["fv"].scene
    x = (np.arange(100) + 0.5) / 100
    ppc0 = scene.initial_ppc
    row = -1
    t = results["fv"].times[row]
    exact = theory.particle_counts_periodic1d(ppc0, 1.0, t)
    vol = scene.cell_volume
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
               title=f"{k}, t = {t:g}, {ensemble} members")
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
    p = argparse.ArgumentParser(prog="python -m ti_dk.figures", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("figure", choices=FIGURES)
    p.add_argument("--ensemble", type=int, help="members (default: 100 for fig2/fig3, 20000 for fig4)")
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
    try:
        sim.init(args.arch)
    except config.ConfigError as exc:
        print(f"ti_dk: error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    fn(args.ensemble or default, Path(args.out), plt)
    print(f"{args.figure}: wrote {Path(args.out) / args.figure}.png and .h5 in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
