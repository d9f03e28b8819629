"""Particle storage for the hybrid: a sparse pool against the flat pool ti_dk uses, and the two
``pool_layout`` choices on whole scenes.

    python benchmarks/bench_pool.py [--cells 256] [--ppc 5] [--fraction 0.1] [--reps 20]
    python benchmarks/bench_pool.py --layouts [--threads 2] [--side 4 8]

Both layouts do what a hybrid step asks of its store: move every particle of a square region
(``fraction`` of a 2D periodic grid) with the same clamped walk, drop those that leave the
region, and leave the survivors ready for the next step.

- sparse: ``pointer`` blocks of 8×8 cells, each with a ``dynamic`` list, double-buffered (a
  ``dynamic`` list cannot remove); a step appends each survivor to its destination block in the
  other buffer, then deactivates the old buffer. Memory follows the occupied blocks.
- flat (ti_dk.pools.ParticlePool): one array per member, survivors marked in place and compacted
  by a blocked exclusive scan into the other buffer; capacity sized from the region.

Prints particle steps per second for both.

``--layouts``: the hybrid with ``pool_layout = flat`` and ``pointer`` (ti_dk.pools.BlockPool) on
ellipse2d (100 steps), sphere3d (30 steps) and sphere3d on 160³ and 254³ cells (5 steps), each in a
process of its own (compare = none): seconds per step after the first (which compiles), the
process's peak RSS, the pool's own fields at their largest, and that the densities agree
(a digest). ``--side`` also runs the pointer layout with other block sides.
"""
import argparse
import math
import os
import time

import taichi as ti

import ti_dk
from ti_dk import load_scene
from ti_dk.core.grid import Grid
from ti_dk.methods.particles import Walker
from ti_dk.core.rng import seed_key

BLK = 8


@ti.data_oriented
class SparsePool:
    def __init__(self, cells: int, max_per_block: int):
        nb = cells // BLK
        self.bufs = []
        for _ in range(2):
            p = ti.Vector.field(4, ti.f64)  # x, y, id, birth
            node = ti.root.pointer(ti.ij, (nb, nb)).dynamic(ti.k, max_per_block, chunk_size=64)
            node.place(p)
            self.bufs.append((p, node))

    @ti.kernel
    def seed(self, p: ti.template(), lo: ti.i32, hi: ti.i32, ppc: ti.i32, h: ti.f64):
        for i, j in ti.ndrange((lo, hi), (lo, hi)):
            for k in range(ppc):
                ti.append(p.parent(), [i // BLK, j // BLK],
                          ti.Vector([(i + ti.random()) * h, (j + ti.random()) * h, (i * 4096 + j) * 64 + k, 0.0]))

    @ti.kernel
    def step(self, walker: ti.template(), src: ti.template(), dst: ti.template(), lo: ti.i32, hi: ti.i32,
             n: ti.i32, h: ti.f64):
        for bi, bj, k in src:
            v = src[bi, bj, k]
            y, alive, _ = walker.move(ti.Vector([v[0], v[1]]), 0, ti.u32(v[2]), ti.u32(v[3]), ti.u32(n))
            ci, cj = ti.cast(ti.floor(y[0] / h), ti.i32), ti.cast(ti.floor(y[1] / h), ti.i32)
            if lo <= ci < hi and lo <= cj < hi:
                ti.append(dst.parent(), [ci // BLK, cj // BLK], ti.Vector([y[0], y[1], v[2], v[3]]))

    @ti.kernel
    def count(self, p: ti.template()) -> ti.i64:
        c = ti.i64(0)
        for bi, bj, k in p:
            c += 1
        return c


def run_sparse(grid, dt, cells, lo, hi, ppc, reps):
    walker = Walker(grid, dt, ti.f64, seed_key(1))
    pool = SparsePool(cells, 64 * BLK * BLK * ppc)
    (a, na), (b, nb) = pool.bufs
    h = 1.0 / cells
    pool.seed(a, lo, hi, ppc, h)
    total = 0
    t = None
    for n in range(reps + 3):
        if n == 3:  # after two warm-up steps (JIT of both buffers' kernels)
            ti.sync()
            t = time.perf_counter()
        total += pool.count(a) if n >= 3 else 0
        pool.step(walker, a, b, lo, hi, n, h)
        na.deactivate_all()  # the whole buffer: its particles now live in the other one
        (a, na), (b, nb) = (b, nb), (a, na)
    ti.sync()
    return total / (time.perf_counter() - t)


def run_flat(cells, fraction, ppc, reps):
    scene = load_scene("equilibrium1d", method="hybrid", cells=[cells, cells], init="uniform", ppc=ppc,
                       regrid_interval=0, threshold=1e-9, t_equil=None, histogram=None, ensemble=1)
    from bench_hybrid import centred_box

    from ti_dk.control.registry import make_solver

    s = make_solver(scene, scene.initial_ppc)
    s.set_region(centred_box((cells, cells), fraction)[None], 0)
    total = 0
    t = None
    for n in range(reps + 3):  # walk + compaction only (no ghosts), as for the sparse pool
        if n == 3:  # after two warm-up steps
            ti.sync()
            t = time.perf_counter()
        total += int(s.n_real.to_numpy()[0]) if n >= 3 else 0
        s.coupling.cross(s.pool, s.cur, n, 1, 1, 0, s.n_cover, 0.0)  # walk, sync, compaction: no ghost ring
    ti.sync()
    return total / (time.perf_counter() - t)


LAYOUT_RUNS = {  # name: (scene, overrides, steps)
    "ellipse2d": ("ellipse2d", {}, 100),
    "sphere3d": ("sphere3d", {}, 30),
    "sphere3d 160³": ("sphere3d", {"cells": [160, 160, 160]}, 5),
    # 256³ itself is refused: the hybrid's 32-bit ids need the padded grid within 2^24 cells
    "sphere3d 254³": ("sphere3d", {"cells": [254, 254, 254]}, 5),
}


def one_layout(name: str, layout: str, side: int | None, threads: int) -> dict:
    """One scene with one layout, in this process: timing, memory and a digest of the densities."""
    import hashlib
    import resource

    from ti_dk.pools import slots
    from ti_dk.control.registry import make_solver

    ti_dk.init("cpu", threads=threads)
    scene_name, overrides, steps = LAYOUT_RUNS[name]
    scene = load_scene(scene_name, compare="none", pool_layout=layout, **overrides)
    if side:
        slots.SIDE[scene.grid.dim] = side
    t0 = time.perf_counter()
    s = make_solver(scene, scene.initial_ppc)
    start = time.perf_counter() - t0
    digest, most, times = hashlib.sha256(), 0, []
    for n in range(steps):
        ti.sync()
        t = time.perf_counter()
        s.step(n)
        ti.sync()
        times.append(time.perf_counter() - t)
        most = max(most, s.pool.nbytes)
        digest.update(s.spde.q.to_numpy().tobytes())
    return {"run": name, "layout": layout, "side": getattr(s.pool, "side", None), "steps": steps,
            "start_s": start, "s_per_step": sum(times[1:]) / (steps - 1), "first_step_s": times[0],
            "median_s": sorted(times[1:])[(steps - 1) // 2],
            "rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, "pool_gib": most / 2**30,
            "particles": s.diagnostics()["particles"], "digest": digest.hexdigest()[:12]}


def compare_layouts(args) -> None:
    """Each run and layout in a process of its own (peak RSS is per process); a Markdown table."""
    import json
    import platform
    import subprocess
    import sys

    print(f"{platform.machine()}, {os.cpu_count()} cores, Taichi {'.'.join(map(str, ti.__version__))}, "
          f"CPU, {args.threads} threads, {time.strftime('%Y-%m-%d %H:%M')}\n")
    print("| run | layout | steps | s/step (mean) | s/step (median) | first step s | start s | peak RSS GiB | "
          "pool fields GiB | particles | density digest |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.runs:
        variants = [("flat", None), ("pointer", None)] + [("pointer", k) for k in args.side]
        for layout, side in variants:
            cmd = [sys.executable, __file__, "--one", name, layout, "--threads", str(args.threads)]
            r = subprocess.run(cmd + (["--side", str(side)] if side else []), capture_output=True, text=True)
            if r.returncode:
                print(f"| {name} | {layout} | failed: {r.stderr.strip().splitlines()[-1]} |")
                continue
            d = json.loads(r.stdout.strip().splitlines()[-1])
            what = layout + (f" ({d['side']} cells/axis)" if d["side"] else "")
            print(f"| {name} | {what} | {d['steps']} | {d['s_per_step']:.4f} | {d['median_s']:.4f} | {d['first_step_s']:.1f} | "
                  f"{d['start_s']:.1f} | {d['rss_gib']:.2f} | {d['pool_gib']:.3f} | {d['particles']:,} | "
                  f"`{d['digest']}` |", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=256)
    ap.add_argument("--ppc", type=int, default=5)
    ap.add_argument("--fraction", type=float, default=0.1)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--layouts", action="store_true", help="compare pool_layout flat and pointer on whole scenes")
    ap.add_argument("--runs", nargs="+", default=list(LAYOUT_RUNS), choices=list(LAYOUT_RUNS))
    ap.add_argument("--side", type=int, nargs="*", default=[], help="--layouts: pointer block sides to try as well")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--one", nargs=2, metavar=("RUN", "LAYOUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        import json
        print(json.dumps(one_layout(*args.one, args.side[0] if args.side else None, args.threads)))
        return
    if args.layouts:
        compare_layouts(args)
        return
    ti_dk.init("cpu")
    side = max(BLK, round(args.cells * math.sqrt(args.fraction)))
    lo, hi = (args.cells - side) // 2, (args.cells - side) // 2 + side
    grid = Grid((args.cells,) * 2, (1.0, 1.0), ((0, 0), (0, 0)), ((0.0, 0.0), (0.0, 0.0)))
    dt = 0.0625 / args.cells**2
    flat = run_flat(args.cells, args.fraction, args.ppc, args.reps)
    sparse = run_sparse(grid, dt, args.cells, lo, hi, args.ppc, args.reps)
    print(f"{args.cells}² grid, {args.fraction:.0%} covered, {args.ppc} ppc: "
          f"flat {flat / 1e6:.1f} M particle-steps/s, sparse pointer+dynamic {sparse / 1e6:.1f} M particle-steps/s "
          f"(flat/sparse = {flat / sparse:.2f})")


if __name__ == "__main__":
    main()
