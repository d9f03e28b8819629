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
for both in every covered cell. Members run in chunks (``member0``: the same streams as one
ensemble of all of them) whose moments are merged exactly.
"""
import argparse
import math
import time

import numpy as np

import ti_dk
from ti_dk.core import theory
from ti_dk.hybrid import regrid


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
    args = ap.parse_args()
    ti_dk.init("cpu", args.threads)
    scene = ti_dk.load_scene("trap1d", method="hybrid", cells=[args.cells], ppc=400 / args.cells, t_end=args.t_end,
                             t_equil=None, output_times=[], regrid_interval=0)
    N = int(round(scene.initial_ppc.sum()))
    p = scene.potential.boltzmann_weights((args.cells,), (1.0,))
    _, covered, _ = regrid.region(scene.initial_ppc, scene.hybrid.regrid, (False,))
    cells = np.flatnonzero(covered)
    print(f"trap1d, hybrid, {args.cells} cells, N = {N}, threshold = {scene.hybrid.threshold}, "
          f"t_end = {args.t_end} ({scene.n_steps} steps), {args.members} members in chunks of {args.chunk}, "
          f"{args.threads} thread(s); covered cells: {cells.tolist()}")
    mean, var, wall = chunked_moments(scene, args.members, args.chunk)
    M = args.members
    print(f"\nwall {wall:.1f} s\n")
    print("| cell | x | N p_i | mean | z(mean) | N p_i q_i | variance | z(var) |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    worst = 0.0
    for i in cells:
        b = theory.binomial_moments(N, float(p[i]))
        mu4 = b["kurtosis"] * b["variance"] ** 2
        z_m = (mean[i] - b["mean"]) / math.sqrt(b["variance"] / M)
        z_v = (var[i] - b["variance"]) / math.sqrt((mu4 - b["variance"] ** 2) / M)
        worst = max(worst, abs(z_m), abs(z_v))
        print(f"| {i} | {(i + 0.5) / args.cells:.4f} | {b['mean']:.5f} | {mean[i]:.5f} | {z_m:+.2f} | "
              f"{b['variance']:.5f} | {var[i]:.5f} | {z_v:+.2f} |")
    verdict = "PASS" if worst < 3 else "FAIL"
    print(f"\nmax |z| = {worst:.2f}: {verdict} (|z| < 3 for mean and variance in every covered cell)")


if __name__ == "__main__":
    main()
