"""Does the hybrid pay for itself? Its ms/step split by phase and kernel, against the fv step, the
particle method and a plain walk of as many particles as the hybrid holds, all in one process.

    python benchmarks/hybrid_value.py ellipse2d --steps 300
    python benchmarks/hybrid_value.py sphere3d --set cells=[64,64,64] --steps 50

The three solvers of the scene (``method`` = hybrid, fv, particle; no compare run, no frames) are
built in one Taichi program (kernel profiler on) and stepped alternately, steps 0 … steps−1, so
that they see the same machine load; step 0 (compilation: the offline cache is on) is timed
apart. Then a fourth solver, the particle method on a uniform density holding the hybrid's mean
particle count on the same grid (the *plain walk*), is timed in blocks alternating with the fv
solver; its time is rescaled by the fv times of the two passes (drift of the shared machine).
Printed (Markdown): wall ms/step of each, the hybrid's phases (``HybridSolver.timing``), its
kernel tasks over 2 % of its step, the kernel-launch overhead (wall minus kernel time), and
``hybrid ÷ (fv + plain walk)``: how much the coupling costs on top of the work it couples.
"""
import argparse
import os
import platform
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import taichi as ti  # noqa: E402
from taichi.lang import impl  # noqa: E402

import ti_dk  # noqa: E402
from ti_dk import load_scene  # noqa: E402
from ti_dk.methods.registry import make_solver  # noqa: E402
from ti_dk.scene.load import parse_value  # noqa: E402


def _timed(f) -> float:
    ti.sync()
    t = time.perf_counter()
    f()
    ti.sync()
    return time.perf_counter() - t


def _kernels(prog, into: dict) -> None:
    """Add the profiler's records since the last clear to ``into`` (task name → seconds)."""
    prog.sync_kernel_profiler()
    prog.update_kernel_profiler()
    for r in prog.get_kernel_profiler_records():  # "<kernel>_c<id>_<n>_kernel_<task>_<kind>"
        task = r.name.split("_c")[0] + ":" + r.name.split("_kernel_")[-1]
        into[task] = into.get(task, 0.0) + 1e-3 * r.kernel_time
    ti.profiler.clear_kernel_profiler_info()


def cpu_model() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        return next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--walk-blocks", type=int, default=3, help="blocks of 10 steps for the plain walk")
    args = p.parse_args()
    over = {}
    for item in args.set:
        k, _, v = item.partition("=")
        over[k.strip()] = parse_value(v.strip(), k.strip())
    over |= dict(compare="none")
    init = ti.init
    ti.init = lambda *a, **kw: init(*a, **{**kw, "kernel_profiler": True})
    ti_dk.init("cpu", args.threads)
    prog = impl.get_runtime().prog
    names = ("hybrid", "fv", "particle")
    scenes = {m: load_scene(args.scene, **over, method=m) for m in names}
    solvers, build, first = {}, {}, {}
    for m in names:
        t = time.perf_counter()
        solvers[m] = make_solver(scenes[m], scenes[m].initial_ppc)
        ti.sync()
        build[m] = time.perf_counter() - t
        first[m] = _timed(lambda: solvers[m].step(0))
    hyb = solvers["hybrid"]
    t_first = dict(hyb.timing)
    for k in hyb.timing:
        hyb.timing[k] = 0.0
    wall = dict.fromkeys(names, 0.0)
    kernels: dict = {}
    count = 0.0
    ti.profiler.clear_kernel_profiler_info()
    steps = args.steps - 1
    for n in range(1, args.steps):
        for m in names:
            wall[m] += _timed(lambda: solvers[m].step(n))
            if m == "hybrid":
                _kernels(prog, kernels)
                count += hyb.diagnostics()["particles"]
            else:
                ti.profiler.clear_kernel_profiler_info()
    mean_n = count / steps
    n_particle = solvers["particle"].diagnostics()["mass"]
    # the plain walk: the particle method on a uniform density holding mean_n particles, same grid
    cells = scenes["hybrid"].grid.cells
    ncell = 1
    for c in cells:
        ncell *= c
    uni = load_scene("equilibrium1d", method="particle", cells=list(cells), init="uniform", ppc=mean_n / ncell,
                     C=scenes["hybrid"].time.C, precision=scenes["hybrid"].method.precision, t_equil=None,
                     histogram=None, ensemble=1, lengths=list(scenes["hybrid"].grid.lengths), compare="none")
    walk = make_solver(uni, uni.initial_ppc)
    walk.step(0)
    w_walk, w_fv = 0.0, 0.0
    n = args.steps
    for b in range(args.walk_blocks):
        for _ in range(10):
            w_walk += _timed(lambda: walk.step(n))
            w_fv += _timed(lambda: solvers["fv"].step(n))
            n += 1
    reps = 10 * args.walk_blocks
    walk_ms = 1e3 * w_walk / reps * (wall["fv"] / steps) / (w_fv / reps)  # at the first pass's fv speed
    ms = {m: 1e3 * wall[m] / steps for m in names}
    print(f"# {args.scene} {' '.join(args.set)}: {time.strftime('%Y-%m-%d %H:%M')}, {cpu_model()}, "
          f"{args.threads} threads, steps 1-{steps} (step 0 apart), f{'32' if uni.method.precision == 'f32' else '64'}\n")
    print("| | ms/step |\n|---|---|")
    print(f"| hybrid | {ms['hybrid']:.2f} |")
    for k, v in hyb.timing.items():
        print(f"| … {k} (HybridSolver.timing) | {1e3 * v / steps:.2f} |")
    ktot = sum(kernels.values())
    print(f"| … kernel time, all tasks | {1e3 * ktot / steps:.2f} |")
    print(f"| … rest: launches, host work, syncs | {ms['hybrid'] - 1e3 * ktot / steps:.2f} |")
    print(f"| fv step alone | {ms['fv']:.2f} |")
    print(f"| particle method alone ({n_particle / 1e6:.2f} M particles) | {ms['particle']:.2f} |")
    print(f"| plain walk of the hybrid's mean {mean_n / 1e3:.0f} k particles (uniform, rescaled) | {walk_ms:.2f} |")
    print(f"| … same, the particle method's per-particle cost × count | {ms['particle'] * mean_n / n_particle:.2f} |")
    print(f"| **hybrid ÷ (fv + plain walk)** | **{ms['hybrid'] / (ms['fv'] + walk_ms):.2f}** |")
    print(f"| particle ÷ hybrid | {ms['particle'] / ms['hybrid']:.2f} |")
    print("\nfirst step (compilation, offline cache on), s: " + ", ".join(
        f"{m} build {build[m]:.2f} + step 0 {first[m]:.2f}" for m in names)
          + "; hybrid step 0 by part: " + ", ".join(f"{k} {v:.2f}" for k, v in t_first.items()))
    print("\n| hybrid kernel task | ms/step | share of step |\n|---|---|---|")
    for task, v in sorted(kernels.items(), key=lambda kv: -kv[1]):
        if v / steps > 0.02 * ms["hybrid"] * 1e-3:
            print(f"| {task} | {1e3 * v / steps:.3f} | {100 * v / wall['hybrid']:.1f} % |")


if __name__ == "__main__":
    main()
