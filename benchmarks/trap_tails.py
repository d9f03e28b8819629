"""Issue 28: the hybrid's particle region in the tails of the harmonic trap (scenes/trap1d.toml:
40 cells, Neumann, σ = 0.08, C = 1/16, N = 400) at >= 10⁵ members, against the exact answer.

    PYTHONPATH=. python benchmarks/trap_tails.py [--members 100000] [--chunk 25000] [--t-end 0.03] [--threads 1]

The scene, its fixed region (where the start holds fewer than ``threshold`` particles per cell,
plus the buffer) and the scoring are those of the slow test
``tests/hybrid/test_solver.py::test_the_trap_tails_follow_the_walks_own_law``
(``tests/helpers.py``: ``trap_tails``, ``tail_scores``): each covered cell's count mean and
variance at t_end (one sample per member: the members are independent) against the exact
Bin(n, p_i) + Poisson(λ p_i) (the start fixes the SPDE's content n and samples the covered cells'
particles, Poisson with mean λ; the particle method places exactly N: λ = 0) in units of their
standard errors, or an exact Poisson tail probability where the expected total is small. Two
answers for p_i: the cell-averaged Boltzmann share (``Potential.boltzmann_weights``, the share the
start and the finite volumes use) and the stationary law of the Euler–Maruyama walk the particles
run (:func:`ti_dk.core.theory.trap_walk_shares`), the criterion. Members run in chunks
(``member0``: the same streams as one ensemble of all of them) whose accumulators are merged
exactly (:meth:`CellStats.merge_row`).
"""
import argparse
import math
import time

import numpy as np
import taichi as ti

import ti_dk
from ti_dk.core.stats import CellStats
from tests.helpers import tail_scores, trap_tails


def chunked_moments(scene, members: int, chunk: int):
    """Per-cell mean and (unbiased) variance of the particle count at t_end over ``members``
    members run ``chunk`` at a time, and the wall seconds."""
    merged, wall = CellStats(scene.grid.cells, scene.grid.cell_volume), 0.0
    cfg = ti.lang.impl.current_cfg()
    arch, threads = "cuda" if cfg.arch == ti.cuda else "cpu", cfg.cpu_max_num_threads
    for start in range(0, members, chunk):
        size = min(chunk, members - start)
        if start:  # a fresh Taichi program: the last chunk's fields are freed (they stay otherwise, and
            ti_dk.init(arch, threads)  # 25,000 members of a 20 × 20 hybrid filled 24 GB by the third chunk)
        t0 = time.perf_counter()
        res = ti_dk.run(scene.replace(ensemble=size), progress=False, member0=start)
        wall += time.perf_counter() - t0
        merged.merge_row(res.rows[-1])
        print(f"  members {start}..{start + size - 1}: {time.perf_counter() - t0:.1f} s", flush=True)
    row, vol = merged.row(), scene.grid.cell_volume
    return row["mean"] * vol, row["variance"] * vol**2, wall


def _fmt(r: dict) -> str:
    """A cell's score: z of the mean and variance, or the exact tail probability."""
    if r["p_value"] is not None:
        return f"P = {r['p_value']:.2f} | –"
    return f"{r['z_mean']:+.2f} | {r['z_var']:+.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=100_000)
    ap.add_argument("--chunk", type=int, default=25_000)
    ap.add_argument("--t-end", type=float, default=0.03)
    ap.add_argument("--cells", type=int, default=40)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--method", default="hybrid", choices=["hybrid", "particle"],
                    help="particle: the same cells of the exact method, to tell the walk's own bias from the coupling's")
    ap.add_argument("--save", help="an .npz file for the per-cell moments (a second look)")
    args = ap.parse_args()
    ti_dk.init("cpu", args.threads)
    M = args.members
    scene, cells, n, lam, q = trap_tails(args.method, M, args.t_end, args.cells)
    p = scene.potential.boltzmann_weights((args.cells,), (1.0,))
    print(f"trap1d, {args.method}, {args.cells} cells, n = {n:.2f} fixed + Poisson({lam:.2f}), threshold = "
          f"{scene.hybrid.threshold}, t_end = {args.t_end} ({scene.n_steps} steps), {M} members in chunks of "
          f"{args.chunk}, {args.threads} thread(s); covered cells: {cells.tolist()}")
    mean, var, wall = chunked_moments(scene, M, args.chunk)
    print(f"\nwall {wall:.1f} s\n")
    if args.save:
        np.savez(args.save, cells=cells, mean=mean, variance=var, members=M, n=n, lam=lam, p=p, p_walk=q)
    boltz, walk = (tail_scores(mean, var, M, n, lam, shares, cells) for shares in (p, q))
    print("| cell | x | exact mean (walk) | mean | exact variance (walk) | variance | z(mean), z(var): Boltzmann "
          "| | walk | |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for b, w in zip(boltz, walk):
        i = w["cell"]
        print(f"| {i} | {(i + 0.5) / args.cells:.4f} | {w['exact_mean']:.5f} | {mean[i]:.5f} | "
              f"{w['exact_variance']:.5f} | {var[i]:.5f} | {_fmt(b)} | {_fmt(w)} |")
    for name, rows in (("Boltzmann", boltz), ("the walk's law", walk)):
        zs = [r["z_mean"] for r in rows if r["z_mean"] is not None]
        zv = [r["z_var"] for r in rows if r["z_var"] is not None]
        pmin = min((r["p_value"] for r in rows if r["p_value"] is not None), default=1.0)
        worst = max(max(map(abs, zs)), max(map(abs, zv)))
        verdict = "PASS" if worst < 3 and pmin >= 0.0027 else "FAIL"
        print(f"\nagainst {name}: max |z(mean)| {max(map(abs, zs)):.2f}, max |z(var)| {max(map(abs, zv)):.2f}, "
              f"mean z(mean) {np.mean(zs):+.2f} (± {1 / math.sqrt(len(zs)):.2f} if unbiased), smallest exact "
              f"P {pmin:.3f}: {verdict}")


if __name__ == "__main__":
    main()
