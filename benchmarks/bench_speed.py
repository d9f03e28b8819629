"""Issue 13's speed table: FV step, particle walk and the hybrid's 3D walk, per thread count, and
(optionally) the same cases on an older source tree, interleaved in one run.

    python benchmarks/bench_speed.py [--threads 1 2] [--before /path/to/old/tree] [--cases fv1d fv2d ...]
                                     [--arch cpu|cuda] [--blocks 3]

Every case runs in a fresh subprocess (Taichi's thread count is fixed at ``ti.init``) with
``PYTHONPATH`` set to the tree under test; a case reports the best of ``--blocks`` timed blocks
after a warm-up step (JIT excluded). ``--clock cpu`` times with the process's CPU time instead of
the wall clock: on a shared machine that is the steadier measure of one thread's work (with two
threads it sums both, so it measures cost, not speed-up). Cases:

- ``fv1d``: 100 periodic cells × 2000 members, C = 0.125, f64: µs per step and member;
- ``fv2d``: 256² periodic, f32, 30 ppc: Mcell/s; ``numpy`` is the same step vectorised in NumPy;
- ``ratio2d``: fv2d's rate over the NumPy step's, the two timed in alternating blocks in one process
  (so both see the same machine load: the figure for "fv2d ≥ k × NumPy" on a shared host);
- ``p1d``: particles, 5 per cell, 100 cells × 2000 members: µs per step and member;
- ``p2d``: particles, 5 per cell, 256²: M particle-steps/s;
- ``walk3d``: particles, 5 per cell, 64³, f64: ns per particle-step of the plain walk;
- ``hybrid3d``: the hybrid on the same grid with a centred box covering half the cells: ns per
  particle-step of its particle part (ghost fill, walk, compaction, sync), real and ghost particles.
"""
import argparse
import json
import math
import os
import subprocess
import sys
import time

CASES = ("fv1d", "fv2d", "numpy", "ratio2d", "p1d", "p2d", "walk3d", "hybrid3d")
UNITS = {"fv1d": "µs/step/member", "fv2d": "Mcell/s", "numpy": "Mcell/s", "ratio2d": "×", "p1d": "µs/step/member",
         "p2d": "M particle-steps/s", "walk3d": "ns/particle-step", "hybrid3d": "ns/particle-step"}


CLOCK = time.perf_counter  # or time.process_time (--clock cpu)


def best_of(step, reps, blocks):
    """Seconds per call of ``step(n)``: the best of ``blocks`` blocks of ``reps`` calls, after one warm-up."""
    import taichi as ti
    step(0)
    ti.sync()
    best, n = math.inf, 1
    for _ in range(blocks):
        t = CLOCK()
        for _ in range(reps):
            step(n)
            n += 1
        ti.sync()
        best = min(best, (CLOCK() - t) / reps)
    return best


def worker(case, threads, arch, blocks):
    import numpy as np

    import ti_dk
    from ti_dk import load_scene
    from ti_dk.control.registry import make_solver

    if case == "numpy":
        return numpy_rate((256, 256), blocks)
    ti_dk.init(arch, threads)

    def scene(method, cells, ppc, ensemble, C=0.0625, precision="f64", **kw):
        return load_scene("equilibrium1d", method=method, cells=list(cells), init="uniform", ppc=ppc, C=C,
                          precision=precision, ensemble=ensemble, t_equil=None, histogram=None, **kw)

    if case in ("fv1d", "fv2d", "ratio2d"):
        sc = scene("fv", (100,), 5.0, 2000, C=0.125) if case == "fv1d" else scene("fv", (256, 256), 30.0, 1, precision="f32")
        s = make_solver(sc, sc.initial_ppc)
        if case == "ratio2d":
            return ratio_2d(s, blocks)
        sec = best_of(s.step, 200 if case == "fv1d" else 100, blocks)
        return 1e6 * sec / 2000 if case == "fv1d" else 256 * 256 / sec / 1e6
    if case in ("p1d", "p2d", "walk3d"):
        cells = {"p1d": (100,), "p2d": (256, 256), "walk3d": (64, 64, 64)}[case]
        sc = scene("particle", cells, 5.0, 2000 if case == "p1d" else 1)
        s = make_solver(sc, sc.initial_ppc)
        sec = best_of(s.step, 50 if case == "p1d" else 20, blocks)
        walked = round(s.diagnostics()["mass"])  # particles (none leave a periodic box)
        return {"p1d": 1e6 * sec / 2000, "p2d": walked / sec / 1e6, "walk3d": 1e9 * sec / walked}[case]
    if case == "hybrid3d":
        cells = (64, 64, 64)
        sc = scene("hybrid", cells, 5.0, 1, regrid_interval=0, threshold=1e-9)
        s = make_solver(sc, sc.initial_ppc)
        mask = np.zeros(cells, dtype=bool)
        side = round(64 * 0.5 ** (1 / 3))
        lo = (64 - side) // 2
        mask[lo:lo + side, lo:lo + side, lo:lo + side] = True
        s.set_region(mask[None], 0)
        s.step(0)
        best = math.inf
        for b in range(blocks):
            spde0 = s.timing["spde"]
            t0, c0 = s.timing["particles"], CLOCK()
            for n in range(1 + 10 * b, 11 + 10 * b):
                s.step(n)
            dt = s.timing["particles"] - t0  # wall time of the particle part
            if CLOCK is not time.perf_counter:  # its share of the CPU time, as the wall-time share
                dt *= (CLOCK() - c0) / (s.timing["particles"] + s.timing["spde"] - t0 - spde0)
            best = min(best, dt / 10)
        r = s.regions if hasattr(s, "regions") else s  # the region moved out of the solver (issue 12)
        ring = r.ring_mask if hasattr(r, "ring_mask") else r.ring.to_numpy()  # a host array since issue 13
        walked = s.diagnostics()["particles"] + int(ring.sum() * 5.0)
        return 1e9 * best / walked
    raise ValueError(case)


def ratio_2d(solver, blocks):
    """``ratio2d``: the best of ``blocks`` blocks of 50 FV steps over the best of as many blocks of
    20 NumPy steps, the blocks alternating in this process."""
    import numpy as np
    import taichi as ti
    from bench_fv import numpy_fv_step
    numpy_step = numpy_fv_step((256, 256), np.float32, 0.0625, 30.0)
    numpy_step()
    solver.step(0)
    ti.sync()
    fv, ref, n = math.inf, math.inf, 1
    for _ in range(blocks):
        t = CLOCK()
        for _ in range(50):
            solver.step(n)
            n += 1
        ti.sync()
        fv = min(fv, (CLOCK() - t) / 50)
        t = CLOCK()
        for _ in range(20):
            numpy_step()
        ref = min(ref, (CLOCK() - t) / 20)
    return ref / fv


def numpy_rate(cells, blocks):
    """The same FV step (eq. 7–9, periodic, f32, C = 1/16, 30 per cell) vectorised in NumPy."""
    import numpy as np
    from bench_fv import numpy_fv_step
    step = numpy_fv_step(cells, np.float32, 0.0625, 30.0)

    step()
    best = math.inf
    for _ in range(blocks):
        t = CLOCK()
        for _ in range(20):
            step()
        best = min(best, (CLOCK() - t) / 20)
    return cells[0] * cells[1] / best / 1e6


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--before", help="an older source tree to measure in the same run (e.g. a git archive of main)")
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    p.add_argument("--arch", default="cpu")
    p.add_argument("--blocks", type=int, default=3)
    p.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args()
    global CLOCK
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    if args.worker:
        print(json.dumps(worker(args.worker, args.threads[0], args.arch, args.blocks)))
        return
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    trees = [("after", here)] + ([("before", os.path.abspath(args.before))] if args.before else [])
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, arch={args.arch}, {args.clock} clock, best of {args.blocks} blocks, trees: "
          + ", ".join(f"{k}={v}" for k, v in trees), flush=True)
    print("| case | unit | threads | " + " | ".join(k for k, _ in trees) + (" | after/before |" if args.before else " |"))
    print("|---|---|---|" + "---|" * (len(trees) + bool(args.before)), flush=True)
    for case in args.cases:
        for t in ([1] if case == "numpy" else args.threads):
            vals = []
            for _, tree in trees:  # interleaved: the trees see the same machine load
                env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [tree, os.environ.get("PYTHONPATH")])))  # keep a --target install
                out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", case, "--threads", str(t),
                                      "--arch", args.arch, "--blocks", str(args.blocks), "--clock", args.clock],
                                     env=env, cwd=tree, capture_output=True, text=True)
                vals.append(float(out.stdout.strip().splitlines()[-1]) if out.returncode == 0 else math.nan)
                if out.returncode:
                    print(out.stderr[-2000:], file=sys.stderr)
            ratio = f" | {vals[0] / vals[1]:.2f} |" if args.before else " |"
            print(f"| {case} | {UNITS[case]} | {t} | " + " | ".join(f"{v:.3g}" for v in vals) + ratio, flush=True)


if __name__ == "__main__":
    main()
