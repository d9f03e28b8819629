"""What a hybrid step costs the host: device syncs and bytes read back and written, per step.

    PYTHONPATH=. python benchmarks/readback.py ellipse2d --set cells=[64,64] --steps 200
    PYTHONPATH=. python benchmarks/readback.py sphere3d --set cells=[32,32,32] --steps 100

Every way Taichi's Python scope touches device data is counted (:func:`ti_dk.core.traffic.counted`
wraps them all, so no code path escapes). The scene runs as ``make_solver`` builds it, stepped ``--steps`` times; steps with a regrid or an
extension (the regrid log grew) are reported apart from the others. On a GPU each sync waits for
the device and each copy crosses PCIe: this is the host's share of a step that issue 40 asks to
keep under 64 bytes read on average.
"""
import argparse

import numpy as np

import ti_dk
from ti_dk.control.registry import make_solver
from ti_dk.core.traffic import counted
from ti_dk.scene.load import command_overrides


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"], help="Taichi backend (benchmarks/gpu.sh: cuda)")
    ap.add_argument("--timed-every", type=int, default=None,
                    help="time every k-th step (HybridSolver.timed_every; a GPU's is 16): the stopwatch's syncs as there")
    args = ap.parse_args()
    ti_dk.init(args.arch, args.threads)
    scene = ti_dk.load_scene(args.scene, method="hybrid", **command_overrides(args.set, {}))
    solver = make_solver(scene, scene.initial_ppc)
    solver.timed_every = args.timed_every or solver.timed_every
    rows = []
    with counted() as t:
        for n in range(min(args.steps, scene.n_steps)):
            before = len(solver.regrids)
            t.reset()
            solver.step(n)
            rows.append((len(solver.regrids) > before, t.syncs, t.read, t.written))
    rows = np.array(rows, dtype=np.int64)
    h = scene.hybrid
    print(f"{args.scene} {'x'.join(map(str, scene.grid.cells))}, {solver.ensemble} member(s), region_from {h.region_from}, "
          f"regrid_floor {h.regrid_floor:g}, {len(rows)} steps (step 0's setup regrid not counted)")
    print("| steps | count | syncs / step | bytes read / step (max) | bytes written / step (max) |")
    print("|---|---|---|---|---|")
    for label, pick in (("all", np.ones(len(rows), bool)), ("with a regrid or extension", rows[:, 0] == 1),
                        ("without", rows[:, 0] == 0)):
        r = rows[pick]
        if len(r):
            print(f"| {label} | {len(r)} | {r[:, 1].mean():.1f} | {r[:, 2].mean():,.0f} ({r[:, 2].max():,}) | "
                  f"{r[:, 3].mean():,.0f} ({r[:, 3].max():,}) |")


if __name__ == "__main__":
    main()
