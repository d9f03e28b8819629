"""The hybrid's particle/SPDE interface against the exact clamped-walk answer (issue 11, case V).

Case V (the authors' 1D case): 100 periodic cells on [0, 1], ``ppc`` particles per cell, cells
41–60 (1-based) empty, the particle region fixed to the void plus one cell each side, C = 0.125,
200 steps. Prints, per ghost profile, the z of the ensemble mean and variance (and skewness and
kurtosis where the exact mean is 0.3–6) in every cell against
:func:`ti_dk.core.theory.particle_counts_periodic`, the region total's variance, and the χ² of the
seed-to-seed (block-to-block) scatter of the region cells' means.

    python benchmarks/hybrid_interface.py --members 100000 --profiles uniform linear mean
"""
import argparse
import math
import time

import numpy as np

import ti_dk
from ti_dk import load_scene
from ti_dk.core import theory
from ti_dk.control.registry import make_solver


def case_v(profile: str, members: int, substeps: int = 1, C: float = 0.125, seed: int = 11):
    return load_scene("void1d", method="hybrid", ppc=12.5, void_lo=0.4, void_hi=0.6, C=C, t_end=0.0025,
                      ensemble=members, regrid_interval=0, ghost_profile=profile, particle_substeps=substeps,
                      seed=seed)


def run_blocks(scene, blocks: int, seeds: bool):
    """Final counts of ``blocks`` blocks of members: consecutive members of one seed, or (``seeds``)
    the same members under seeds 1, 2, …"""
    out = []
    for b in range(blocks):
        sc = scene.replace(seed=b + 1) if seeds else scene
        s = make_solver(sc, sc.initial_ppc, member0=0 if seeds else b * sc.method.ensemble)
        for n in range(sc.n_steps):
            s.step(n)
        out.append(s.density() * s.grid.cell_volume)
        region = s.region()[0]
    return np.concatenate(out), region, scene.n_steps


def chi2_sf(x: float, k: int) -> float:
    """P(χ²_k > x), Wilson–Hilferty."""
    z = ((x / k) ** (1 / 3) - (1 - 2 / (9 * k))) / math.sqrt(2 / (9 * k))
    return 0.5 * math.erfc(z / math.sqrt(2))


def report(counts, region, scene, steps, blocks):
    N = counts.shape[0]
    ppc0 = scene.initial_ppc
    sub = scene.hybrid.particle_substeps
    exact = theory.particle_counts_periodic(ppc0, 1.0, scene.dt / sub, steps * sub)
    brownian = theory.particle_counts_periodic(ppc0, 1.0, scene.dt, steps, clamp=False)
    k2, k4 = exact["variance"], (exact["kurtosis"] - 3) * exact["variance"] ** 2
    mean, var = counts.mean(0), counts.var(0, ddof=1)
    z_mean = (mean - exact["mean"]) / np.sqrt(k2 / N)
    z_var = (var - k2) / np.sqrt((k4 + 2 * k2**2) / N)
    z_brown = (mean - brownian["mean"]) / np.sqrt(k2 / N)
    linear = sub == 1 and scene.hybrid.ghost_profile in ("mean", "uniform")  # the hybrid's own mean is known
    hybrid = theory.hybrid_mean_1d(ppc0, region, scene.dt, steps, ghost_profile=scene.hybrid.ghost_profile) if linear \
        else np.full(len(ppc0), np.nan)
    z_hyb = (mean - hybrid) / np.sqrt(k2 / N)
    lines = ["cell  region  exact_mean  z_mean  exact_var  z_var  z_skew  z_kurt  z_mean_unclamped  "
             "hybrid_mean  z_vs_hybrid"]
    d = counts - mean
    skew = (d**3).mean(0) / (d**2).mean(0) ** 1.5
    kurt = (d**4).mean(0) / (d**2).mean(0) ** 2
    P = theory.cell_transition(100, 1.0, scene.dt / sub, steps * sub)
    low = region & (exact["mean"] >= 0.3) & (exact["mean"] <= 6)
    _, se = theory.void_reference(ppc0, 1.0, scene.dt / sub, steps * sub, N, low, replicas=60)
    zs_all = (skew - exact["skewness"]) / se["skewness"]  # NaN outside the low-density covered cells
    zk_all = (kurt - exact["kurtosis"]) / se["kurtosis"]
    for i in range(34, 67):
        lines.append(f"{i + 1:4d}  {'P' if region[i] else '.':6s}  {exact['mean'][i]:10.4f}  {z_mean[i]:6.2f}  "
                     f"{k2[i]:9.4f}  {z_var[i]:6.2f}  {zs_all[i]:6.2f}  {zk_all[i]:6.2f}  {z_brown[i]:16.2f}  "
                     f"{hybrid[i]:11.4f}  {z_hyb[i]:11.2f}")
    t = theory.count_in_cells(ppc0, P, region)
    tot = counts[:, region].sum(1)
    tot_mean, tot_var, tot_k4 = t["mean"], t["variance"], (t["kurtosis"] - 3) * t["variance"] ** 2
    z_tot = (tot.var(ddof=1) - tot_var) / math.sqrt((tot_k4 + 2 * tot_var**2) / N)
    lines.append(f"region total: mean {tot.mean():.3f} vs exact {tot_mean:.3f} (z = "
                 f"{(tot.mean() - tot_mean) / math.sqrt(tot_var / N):.2f}); variance {tot.var(ddof=1):.3f} vs exact "
                 f"{tot_var:.3f} (z = {z_tot:.2f})")
    h_tot = hybrid[region].sum()
    lines.append(f"region total: the hybrid's own expectation (theory.hybrid_mean_1d) {h_tot:.3f} "
                 f"(z = {(tot.mean() - h_tot) / math.sqrt(tot_var / N):.2f})")
    # block-to-block (seed-to-seed) scatter of the region total's mean against the within-block error
    B = counts[:, region].sum(1).reshape(blocks, -1)
    z = (B.mean(1) - B.mean()) / np.sqrt(B.var(1, ddof=1) / B.shape[1])
    chi2 = float((z**2).sum())
    lines.append(f"block scatter of the region total: chi2 = {chi2:.1f} on {blocks - 1} dof, "
                 f"p = {chi2_sf(chi2, blocks - 1):.3f}")
    worst = {"mean": np.abs(z_mean).max(), "var(region)": np.abs(z_var[region]).max(),
             "mean vs unclamped (region)": np.abs(z_brown[region]).max(), "mean vs hybrid": np.abs(z_hyb).max()}
    lines.append("max |z|: " + ", ".join(f"{k} {v:.2f}" for k, v in worst.items()))
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--members", type=int, default=20000)
    ap.add_argument("--blocks", type=int, default=10)
    ap.add_argument("--profiles", nargs="+", default=["uniform", "linear", "mean"])
    ap.add_argument("--substeps", type=int, default=1)
    ap.add_argument("--C", type=float, default=0.125)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seeds", action="store_true", help="blocks are seeds 1, 2, … (else members of seed 11)")
    a = ap.parse_args()
    ti_dk.init("cpu", threads=a.threads)
    for prof in a.profiles:
        scene = case_v(prof, a.members // a.blocks, a.substeps, a.C)
        t = time.perf_counter()
        counts, region, steps = run_blocks(scene, a.blocks, a.seeds)
        print(f"## ghost_profile = {prof}, substeps = {a.substeps}, C = {a.C}, {counts.shape[0]} members in "
              f"{a.blocks} {'seeds' if a.seeds else 'blocks'} "
              f"({time.perf_counter() - t:.0f} s)")
        print(report(counts, region, scene, steps, a.blocks), flush=True)


if __name__ == "__main__":
    main()
