"""What the drift of an external potential costs: each method's step time on the trap1d scene (1D)
and a 2D trap, with the potential and without (the same start, the same grid), in one process.

    python benchmarks/bench_potential.py [--members 2000] [--steps 200]

Prints a Markdown table: seconds per step with and without the potential and their ratio: the
two solvers built side by side, a first step each (compiling), then ``repeats`` rounds that time
``steps`` steps of one and then of the other, the best round of each (alternating, so that a busy
machine slows both alike).
"""
import argparse
import time

import taichi as ti

import ti_dk
from ti_dk.control.registry import make_solver

CASES = {  # name: scene overrides (trap1d's start: the Boltzmann profile of its potential)
    "1D, 40 cells": dict(),
    "2D, 64x64": dict(cells=[64, 64], potential="0.5*((x-0.5)/0.15)**2 + 0.5*((y-0.5)/0.15)**2"),
}


def step_times(scenes, ppc, steps: int, repeats: int) -> list[float]:
    """Seconds per step of each scene's solver (best round), alternating between them."""
    solvers = [make_solver(scene, ppc) for scene in scenes]
    for solver in solvers:
        solver.step(0)
    best = [float("inf")] * len(solvers)
    for rep in range(repeats):
        for k, solver in enumerate(solvers):
            ti.sync()
            t = time.perf_counter()
            for n in range(steps):
                solver.step(1 + rep * steps + n)
            ti.sync()
            best[k] = min(best[k], (time.perf_counter() - t) / steps)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=2000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    ti_dk.init("cpu")
    print("| case | method | members | with U [ms/step] | without [ms/step] | ratio |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    for case, kw in CASES.items():
        for method in ("fv", "gaussian", "particle", "hybrid"):
            members = args.members if case.startswith("1D") else max(1, args.members // 100)
            scene = ti_dk.load_scene("trap1d", method=method, ensemble=members, regrid_interval=0, **kw)
            with_u, without = step_times([scene, scene.replace(potential="", init="uniform")], scene.initial_ppc, args.steps,
                                         args.repeats)
            print(f"| {case} | {method} | {members} | {1e3 * with_u:.3f} | {1e3 * without:.3f} | "
                  f"{with_u / without:.2f} |", flush=True)


if __name__ == "__main__":
    main()
