"""What the drift of an external potential costs: each method's step time on the trap1d scene (1D)
and a 2D trap, with the potential and without (the same start, the same grid), in one process.

    python benchmarks/bench_potential.py [--members 2000] [--steps 200]

Prints a Markdown table: seconds per step with and without the potential and their ratio (the
best of three repeats of ``steps`` steps each, after a first step that compiles the kernels).
"""
import argparse
import time

import taichi as ti

import ti_dk
from ti_dk.methods.registry import make_solver

CASES = {  # name: scene overrides (trap1d's start: the Boltzmann profile of its potential)
    "1D, 40 cells": dict(),
    "2D, 64x64": dict(cells=[64, 64], potential="0.5*((x-0.5)/0.15)**2 + 0.5*((y-0.5)/0.15)**2"),
}


def step_time(scene, ppc, steps: int) -> float:
    """Seconds per step (best of three), kernels compiled first."""
    solver = make_solver(scene, ppc)
    solver.step(0)
    ti.sync()
    best = float("inf")
    for rep in range(3):
        t = time.perf_counter()
        for n in range(steps):
            solver.step(1 + rep * steps + n)
        ti.sync()
        best = min(best, (time.perf_counter() - t) / steps)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=2000)
    ap.add_argument("--steps", type=int, default=200)
    args = ap.parse_args()
    ti_dk.init("cpu")
    print("| case | method | members | with U [ms/step] | without [ms/step] | ratio |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    for case, kw in CASES.items():
        for method in ("fv", "gaussian", "particle", "hybrid"):
            members = args.members if case.startswith("1D") else max(1, args.members // 100)
            scene = ti_dk.load_scene("trap1d", method=method, ensemble=members, regrid_interval=0, **kw)
            ppc = scene.initial_ppc
            with_u = step_time(scene, ppc, args.steps)
            without = step_time(scene.replace(potential=""), ppc, args.steps)
            print(f"| {case} | {method} | {members} | {1e3 * with_u:.3f} | {1e3 * without:.3f} | "
                  f"{with_u / without:.2f} |", flush=True)


if __name__ == "__main__":
    main()
