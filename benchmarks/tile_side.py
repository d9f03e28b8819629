"""Which tile side makes the hybrid cheapest? Hybrids of one scene with different ``tile`` sides,
built in one Taichi program and stepped alternately through the whole run (the same machine load),
with the particle method's steps spread over it for the ratio (issue 40: the region of tiles).

    python benchmarks/tile_side.py ellipse2d --sides 4 2 1 --particle-steps 60 --set ppc_outer=300 --set ppc_inner=150
    python benchmarks/tile_side.py sphere3d --set cells=[64,64,64] --particle-steps 10

Printed (Markdown): per side the hybrid's ms/step, its mean particle count, and particle ÷ hybrid.
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import taichi as ti  # noqa: E402

import ti_dk  # noqa: E402
from ti_dk import load_scene  # noqa: E402
from ti_dk.control.registry import make_solver  # noqa: E402
from ti_dk.scene.load import parse_value  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--sides", type=int, nargs="+", default=[4, 2, 1])
    p.add_argument("--particle-steps", type=int, default=20)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    over = {k.strip(): parse_value(v.strip(), k.strip()) for k, _, v in (item.partition("=") for item in args.set)}
    over["compare"] = "none"
    ti_dk.init("cpu", args.threads)
    solvers = {}
    for side in args.sides:
        sc = load_scene(args.scene, **{**over, "tile": side}, method="hybrid")
        solvers[f"tile {side}"] = make_solver(sc, sc.initial_ppc)
    ref = load_scene(args.scene, **over, method="particle")
    solvers["particle"] = make_solver(ref, ref.initial_ppc)
    steps = sc.n_steps
    for s in solvers.values():
        s.step(0)
    stride = max(1, (steps - 1) // max(1, args.particle_steps - 1))
    wall, taken, count = dict.fromkeys(solvers, 0.0), dict.fromkeys(solvers, 0), dict.fromkeys(solvers, 0.0)
    for n in range(1, steps):
        for m, s in solvers.items():
            if m == "particle" and ((n - 1) % stride or taken[m] >= args.particle_steps - 1):
                continue
            taken[m] += 1
            ti.sync()
            t = time.perf_counter()
            s.step(taken[m])
            ti.sync()
            wall[m] += time.perf_counter() - t
            if m != "particle":
                count[m] += s.diagnostics()["particles"]
    ms = {m: 1e3 * wall[m] / taken[m] for m in solvers}
    print(f"# {args.scene} {' '.join(args.set)}: {time.strftime('%Y-%m-%d %H:%M')}, {args.threads} threads, "
          f"steps 1-{steps - 1} (particle method {taken['particle']} of them, spread), load average "
          f"{os.getloadavg()[0]:.1f}\n")
    print(f"particle method: {ms['particle']:.2f} ms/step\n")
    print("| tile side | hybrid ms/step | mean particles | particle ÷ hybrid |\n|---|---|---|---|")
    for m in solvers:
        if m != "particle":
            print(f"| {m[5:]} | {ms[m]:.2f} | {count[m] / taken[m] / 1e3:.0f} k | {ms['particle'] / ms[m]:.2f} |")


if __name__ == "__main__":
    main()
