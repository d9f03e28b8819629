"""Issue 28: the hybrid's particle region in the tails of the harmonic trap (scenes/trap1d.toml:
40 cells, Neumann, σ = 0.08, C = 1/16, N = 400) at >= 10⁵ members, against the exact answer.

    PYTHONPATH=. python benchmarks/trap_tails.py [--members 100000] [--chunk 25000] [--t-end 0.05] [--threads 1]

At equilibrium N non-interacting particles with their total fixed by the Neumann walls fill cell i
as Bin(N, p_i), p_i the cell's Boltzmann share (``Potential.boltzmann_weights``: the cell average
of e^{-U}, the share the start and the finite volumes use). The hybrid's region is fixed
(``regrid_interval = 0``) where the start holds fewer than ``threshold`` particles per cell (plus
the buffer): those covered cells hold particles only, and their count's ensemble mean and variance
at t_end (one sample per member: no pooling over time, so the members are independent) are
compared with N p_i and N p_i (1 − p_i) in units of their standard errors (from the exact
binomial central moments: SE(mean) = sqrt(var/M), SE(s²) = sqrt((μ₄ − var²)/M)). Pass: |z| < 3
for both in every covered cell. Beside it, the z-scores against the Euler–Maruyama walk's own
stationary law (:func:`walk_shares`), which the particles follow wherever the SPDE does not reach.
Members run in chunks (``member0``: the same streams as one ensemble of all of them) whose moments
are merged exactly.
"""
import argparse
import math
import time

import numpy as np

import ti_dk
from ti_dk.core import theory
from ti_dk.hybrid import regrid


def walk_shares(scene, cells: int) -> np.ndarray:
    """Each cell's share of the Euler–Maruyama walk's own stationary law in the trap
    (:func:`theory.harmonic_walk_shares`, U'' by central differences)."""
    h = 1e-4
    k = float((scene.potential(np.array(0.5 + h)) - 2 * scene.potential(np.array(0.5))
               + scene.potential(np.array(0.5 - h))) / h**2)
    return theory.harmonic_walk_shares(k, scene.dt, cells)


def z_scores(N: int, p: float, M: int, mean: float, var: float) -> tuple[dict, float, float]:
    """Bin(N, p)'s moments and the z-scores of an ensemble's mean and variance of M members."""
    b = theory.binomial_moments(N, p)
    mu4 = b["kurtosis"] * b["variance"] ** 2
    return (b, (mean - b["mean"]) / math.sqrt(b["variance"] / M),
            (var - b["variance"]) / math.sqrt((mu4 - b["variance"] ** 2) / M))


def chunked_moments(scene, members: int, chunk: int):
    """Per-cell mean and (unbiased) variance of the particle count at t_end over ``members``
    members run ``chunk`` at a time, and the wall seconds."""
    n, mean, m2, wall = 0, 0.0, 0.0, 0.0
    for start in range(0, members, chunk):
        size = min(chunk, members - start)
        t0 = time.perf_counter()
        res = ti_dk.run(scene.replace(ensemble=size), progress=False, member0=start)
        wall += time.perf_counter() - t0
        mu_c = res.stats.mean[-1] * res.cell_volume
        var_c = res.stats.variance[-1] * res.cell_volume**2
        delta = mu_c - mean
        tot = n + size
        mean = mean + delta * size / tot
        m2 = m2 + var_c * (size - 1) + delta**2 * n * size / tot  # Chan et al.'s pairwise merge
        n = tot
        print(f"  members {start}..{start + size - 1}: {time.perf_counter() - t0:.1f} s", flush=True)
    return mean, m2 / (n - 1), wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=100_000)
    ap.add_argument("--chunk", type=int, default=25_000)
    ap.add_argument("--t-end", type=float, default=0.05)
    ap.add_argument("--cells", type=int, default=40)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--method", default="hybrid", choices=["hybrid", "particle"],
                    help="particle: the same cells of the exact method, to tell the walk's own bias from the coupling's")
    ap.add_argument("--save", help="an .npz file for the per-cell moments (a second look)")
    args = ap.parse_args()
    ti_dk.init("cpu", args.threads)
    scene = ti_dk.load_scene("trap1d", method=args.method, cells=[args.cells], ppc=400 / args.cells, t_end=args.t_end,
                             t_equil=None, output_times=[], regrid_interval=0)
    N = int(round(scene.initial_ppc.sum()))
    p = scene.potential.boltzmann_weights((args.cells,), (1.0,))
    q = walk_shares(scene, args.cells)
    _, covered, _ = regrid.region(scene.initial_ppc, scene.hybrid.regrid, (False,))
    cells = np.flatnonzero(covered)
    print(f"trap1d, {args.method}, {args.cells} cells, N = {N}, threshold = {scene.hybrid.threshold}, "
          f"t_end = {args.t_end} ({scene.n_steps} steps), {args.members} members in chunks of {args.chunk}, "
          f"{args.threads} thread(s); covered cells: {cells.tolist()}")
    mean, var, wall = chunked_moments(scene, args.members, args.chunk)
    M = args.members
    print(f"\nwall {wall:.1f} s\n")
    if args.save:
        np.savez(args.save, cells=cells, mean=mean, variance=var, members=M, N=N, p=p, p_walk=q)
    print("| cell | x | N p_i | mean | z(mean) | N p_i q_i | variance | z(var) | z(mean), walk | z(var), walk |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    worst, worst_walk = 0.0, 0.0
    for i in cells:
        b, z_m, z_v = z_scores(N, float(p[i]), M, mean[i], var[i])
        _, w_m, w_v = z_scores(N, float(q[i]), M, mean[i], var[i])
        worst, worst_walk = max(worst, abs(z_m), abs(z_v)), max(worst_walk, abs(w_m), abs(w_v))
        print(f"| {i} | {(i + 0.5) / args.cells:.4f} | {b['mean']:.5f} | {mean[i]:.5f} | {z_m:+.2f} | "
              f"{b['variance']:.5f} | {var[i]:.5f} | {z_v:+.2f} | {w_m:+.2f} | {w_v:+.2f} |")
    zs = [z_scores(N, float(p[i]), M, mean[i], var[i])[1] for i in cells]
    print(f"\nmean of z(mean) over the covered cells: {np.mean(zs):+.2f} (± {1 / math.sqrt(len(zs)):.2f} "
          "if unbiased); "
          f"max |z| against the walk's own law: {worst_walk:.2f}")
    verdict = "PASS" if worst < 3 else "FAIL"
    print(f"\nmax |z| = {worst:.2f}: {verdict} (|z| < 3 for mean and variance in every covered cell)")


if __name__ == "__main__":
    main()
