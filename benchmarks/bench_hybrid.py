"""Cost of a hybrid step against an fv step on the same grid, as the covered fraction grows.

    python benchmarks/bench_hybrid.py [--cells 256 256] [--ppc 5] [--reps 30]

Uniform density (``--ppc`` particles per cell), periodic, region fixed to a centred box covering
0, 1, 10, 50 and 100 % of the cells. Prints a Markdown table: ms per step, the ratio to the fv
step measured in the same run, particle steps per second (real + ghost particles walked), and the
cost of one regrid (tag + Berger–Rigoutsos + resampling) on the ellipse2d state.
"""
import argparse
import math
import platform
import time

import numpy as np
import taichi as ti

import ti_dk
from ti_dk import load_scene
from ti_dk.control.registry import make_solver


def per_step(solver, reps, blocks=5):
    """Seconds per step: the best of ``blocks`` blocks of ``reps`` steps (this shared machine is noisy)."""
    solver.step(0)
    best = math.inf
    for b in range(blocks):
        ti.sync()
        t = time.perf_counter()
        for n in range(1 + b * reps, 1 + (b + 1) * reps):
            solver.step(n)
        ti.sync()
        best = min(best, (time.perf_counter() - t) / reps)
    return best


def centred_box(cells, fraction):
    mask = np.zeros(cells, dtype=bool)
    if fraction > 0:
        side = [max(1, round(n * fraction ** (1 / len(cells)))) for n in cells]
        mask[tuple(slice((n - s) // 2, (n - s) // 2 + s) for n, s in zip(cells, side))] = True
    return mask


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, nargs="+", default=[256, 256])
    ap.add_argument("--ppc", type=float, default=5.0)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--arch", default="cpu")
    args = ap.parse_args()
    ti_dk.init(args.arch)
    common = dict(cells=args.cells, init="uniform", ppc=args.ppc, t_equil=None, histogram=None, ensemble=1)
    fv_scene = load_scene("equilibrium1d", method="fv", **common)
    ppc = fv_scene.initial_ppc
    fv = make_solver(fv_scene, ppc)
    per_step(fv, args.reps, 2)  # warm the machine up
    fv_ms = 1e3 * per_step(fv, args.reps)
    print(f"{platform.processor() or platform.machine()}, {args.arch}, cells {args.cells}, {args.ppc} ppc, "
          f"{time.strftime('%Y-%m-%d')}\n")
    print(f"fv step: {fv_ms:.2f} ms\n")
    print("| covered | hybrid ms/step | hybrid / fv | particles walked per step | M particle-steps/s |")
    print("|---|---|---|---|---|")
    hyb_scene = load_scene("equilibrium1d", method="hybrid", regrid_interval=0, threshold=1e-9, **common)
    s = make_solver(hyb_scene, ppc)  # one solver (kernels compiled once), its region reset per row
    for fraction in (0.0, 0.01, 0.1, 0.5, 1.0):
        s.spde.initialize(ppc)
        s.set_region(centred_box(tuple(args.cells), fraction)[None], 0)
        ms = 1e3 * per_step(s, args.reps)
        walked = s.diagnostics()["particles"] + int(s.regions.ring_mask.sum() * args.ppc)
        print(f"| {100 * fraction:g} % | {ms:.2f} | {ms / fv_ms:.2f} | {walked} | {walked / ms / 1e3:.1f} |")
    ell = load_scene("ellipse2d", cells=args.cells)
    s = make_solver(ell, ell.initial_ppc)
    for n in range(50):
        s.step(n)
    ti.sync()
    t = time.perf_counter()
    for k in range(5):
        s.regrid(50 + k)
    ti.sync()
    r = s.regrids[-1]
    print(f"\nregrid on ellipse2d after 50 steps: {1e3 * (time.perf_counter() - t) / 5:.1f} ms "
          f"({r['boxes']} boxes, {r['covered_cells']} covered cells, efficiency {r['efficiency']:.2f})")


if __name__ == "__main__":
    main()
