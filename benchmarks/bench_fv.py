"""FV / Gaussian step throughput against NumPy and against ceilings measured in the same run.

    python benchmarks/bench_fv.py [--arch cpu|cuda] [--quick]

Prints a Markdown table (cell-updates per second). Ceilings: the normal-generation rate of the
same Philox + table-normal code (a cell needs one normal per axis) and the memory bandwidth of a
streaming copy (a cell update moves at least q in/out plus dim fluxes in/out).
"""
import argparse
import platform
import time

import numpy as np
import taichi as ti

import ti_dk
from ti_dk.core import rng
from ti_dk.methods.fv import SPDESolver
from ti_dk.core.grid import Grid


def timed(fn, reps):
    fn()
    ti.sync()
    t = time.perf_counter()
    for i in range(reps):
        fn(i)
    ti.sync()
    return (time.perf_counter() - t) / reps


def periodic_grid(cells):
    return Grid(cells, (1.0,) * len(cells), ((0, 0),) * len(cells), ((0.0, 0.0),) * len(cells))


def solver_rate(cells, ensemble, real, gaussian, reps):
    grid = periodic_grid(cells)
    s = SPDESolver(grid, 0.1 * min(grid.dx) ** 2, ensemble, rng.seed_key(1), real, gaussian)
    s.initialize(np.full(cells, 30.0))
    sec = timed(lambda n=0: s.step(n), reps)
    return ensemble * np.prod(cells) / sec


def numpy_fv_step(cells, dtype, C, ppc):
    """One FV step (eq. 7-9, periodic, unit box) vectorised in NumPy, normals from default_rng: the
    reference a one-page script would be. Returns ``step()``."""
    q = np.full(cells, ppc * np.prod(cells), dtype=dtype)
    h = 1.0 / cells[0]
    dt = C * h * h
    scale = dtype(1.0 / np.sqrt(dt * h ** len(cells)))
    g = np.random.default_rng(1)

    def step(_=0):
        nonlocal q
        sq = np.sqrt(np.maximum(q, 0))
        dq = np.zeros_like(q)
        for a in range(len(cells)):
            right = np.roll(q, -1, axis=a)
            F = dtype(0.5 / h) * (right - q) + scale * dtype(0.5) * (sq + np.roll(sq, -1, axis=a)) \
                * g.standard_normal(cells, dtype=dtype)
            dq += (F - np.roll(F, 1, axis=a)) * dtype(1 / h)
        q = q + dtype(dt) * dq

    return step


def numpy_rate(cells, real, reps):
    """Cells per second of :func:`numpy_fv_step`."""
    step = numpy_fv_step(cells, np.float32 if real == ti.f32 else np.float64, 0.1, 3000.0 / np.prod(cells))
    step()
    t = time.perf_counter()
    for _ in range(reps):
        step()
    return np.prod(cells) / ((time.perf_counter() - t) / reps)


def normal_ceiling(real, n=1 << 23):
    rng.prepare()
    out = ti.field(real, shape=n)

    @ti.kernel
    def fill(step: ti.u32):
        for i in range(n // 4):
            r = rng.philox4x32(ti.math.uvec4(ti.u32(i), step, 0, 0), ti.math.uvec2(1, 2))
            for w in ti.static(range(4)):
                out[4 * i + w] = rng.normal(r[w], real)

    return n / timed(lambda k=0: fill(k), 10)


def bandwidth(n=1 << 25):
    a = ti.field(ti.f32, shape=n)
    b = ti.field(ti.f32, shape=n)

    @ti.kernel
    def copy():
        for i in a:
            b[i] = a[i]

    return 2 * 4 * n / timed(lambda k=0: copy(), 10)  # bytes per second


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--arch", default="cpu")
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    ti_dk.init(args.arch)
    reps = 5 if args.quick else 30
    bw = bandwidth()
    print(f"# {platform.processor() or platform.machine()}, arch={args.arch}, {time.strftime('%Y-%m-%d')}")
    print(f"memory bandwidth (copy): {bw / 1e9:.1f} GB/s")
    print("| case | precision | fv Mcell/s | gaussian Mcell/s | NumPy fv Mcell/s | normal ceiling Mcell/s | bandwidth ceiling Mcell/s |")
    print("|---|---|---|---|---|---|---|")
    for label, cells, ens in (("2D 256²", (256, 256), 1), ("3D 128³", (128, 128, 128), 1),
                              ("1D 100 × 20000 members", (100,), 20000)):
        for real, name in ((ti.f32, "f32"), (ti.f64, "f64")):
            fv = solver_rate(cells, ens, real, False, reps)
            ga = solver_rate(cells, ens, real, True, reps)
            npr = numpy_rate(cells, real, max(2, reps // 5)) if ens == 1 else float("nan")
            normal = normal_ceiling(real) / len(cells)
            size = 4 if name == "f32" else 8
            moved = size * (2 + 2 * len(cells) + len(cells))  # q r/w, flux write + read twice (lower, upper)
            print(f"| {label} | {name} | {fv / 1e6:.1f} | {ga / 1e6:.1f} | {npr / 1e6:.1f} | {normal / 1e6:.1f} | "
                  f"{bw / moved / 1e6:.0f} |")


if __name__ == "__main__":
    main()
