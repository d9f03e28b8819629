"""Does the hybrid pay for itself? Its ms/step split by phase and kernel, against the fv step, the
particle method and a plain walk of as many particles as the hybrid holds, all in one process.

    python benchmarks/hybrid_value.py ellipse2d --steps 300
    python benchmarks/hybrid_value.py sphere3d --set cells=[64,64,64] --steps 50
    python benchmarks/hybrid_value.py ellipse2d --whole --particle-steps 100   # the whole run

The three solvers of the scene (``method`` = hybrid, fv, particle; no compare run, no frames) and
a fourth, the *plain walk* (the particle method on a uniform density holding as many particles as
the hybrid after its step 0, same grid), are built in one Taichi program and stepped
alternately, steps 1 … steps−1, so that they see the same machine load; step 0 (compilation:
the offline cache is on) is timed apart. The plain walk's time is scaled per particle to the
hybrid's mean count. Printed (Markdown): wall ms/step of each, the hybrid's phases
(``HybridSolver.timing``), and ``hybrid ÷ (fv + plain walk)``: what the coupling costs on top of
the work it couples; with ``--kernels`` also its kernel tasks over 2 % of its step and what is
not kernel time (launches, host work). The kernel profiler times every task apart and so adds
to every launch: with it on the hybrid, which launches most, measured 1.2× slower (ellipse2d),
so the ratios are taken with it off unless ``--kernels`` is given.

``--whole`` steps the hybrid and fv through the scene's whole run (a user pays for all of it:
the region shrinks as the void fills) and prints the hybrid's cost per tenth of the run; the
particle method and the plain walk take ``--particle-steps`` steps only, as their cost per step
does not depend on the state (a fixed number of particles on a periodic grid: not so with
Dirichlet sides, where the script says so), spread evenly over the hybrid's run: this VM's speed,
the particle method's above all (memory-bound at 15 M particles), drifts by a third between runs
minutes apart, so a ratio of figures taken at different times moved with it (26–34 for the same code).
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
from ti_dk.control.registry import make_solver  # noqa: E402
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


def _plain_walk(sc, count: float):
    """The particle method on a uniform density holding about ``count`` particles, on the grid of ``sc``."""
    ncell = 1
    for c in sc.grid.cells:
        ncell *= c
    uni = load_scene("equilibrium1d", method="particle", cells=list(sc.grid.cells), init="uniform",
                     ppc=count / ncell, C=sc.time.C, precision=sc.method.precision, t_equil=None, histogram=None,
                     ensemble=1, lengths=list(sc.grid.lengths), compare="none")
    return make_solver(uni, uni.initial_ppc)


def measure(solvers: dict, steps: int, short: int, prog) -> tuple[dict, dict, float, list]:
    """Steps 1 … steps−1 of the hybrid and fv, 1 … short−1 of the others (one every ``stride`` of the
    hybrid's, so that their samples span the same stretch of time), alternating: wall seconds
    per solver, the hybrid's kernel tasks (seconds; ``prog`` None: not profiled), its mean particle
    count, and per tenth of the steps its (seconds, particle count sum, steps)."""
    hyb = solvers["hybrid"]
    for k in hyb.timing:
        hyb.timing[k] = 0.0
    wall = dict.fromkeys(solvers, 0.0)
    kernels: dict = {}
    count = 0.0
    tenths = [[0.0, 0.0, 0] for _ in range(10)]
    if prog:
        ti.profiler.clear_kernel_profiler_info()
    stride = max(1, (steps - 1) // max(1, short - 1))  # the short ones spread over the run: the same machine load
    taken = dict.fromkeys(solvers, 0)
    for n in range(1, steps):
        for m, s in solvers.items():
            if m in ("particle", "walk") and ((n - 1) % stride or taken[m] >= short - 1):
                continue
            taken[m] += 1
            dt = _timed(lambda: s.step(taken[m]))
            wall[m] += dt
            if m == "hybrid":
                if prog:
                    _kernels(prog, kernels)
                c = hyb.diagnostics()["particles"]
                count += c
                w = tenths[min(9, 10 * (n - 1) // max(1, steps - 1))]
                w[0], w[1], w[2] = w[0] + dt, w[1] + c, w[2] + 1
            elif prog:
                ti.profiler.clear_kernel_profiler_info()
    return wall, kernels, count / (steps - 1), tenths


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--whole", action="store_true", help="the hybrid and fv over the scene's whole run")
    p.add_argument("--particle-steps", type=int, default=None,
                   help="steps of the particle method and the plain walk (default: --steps)")
    p.add_argument("--kernels", action="store_true", help="kernel profiler on: the table of kernel tasks")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--arch", default="cpu", choices=["cpu", "cuda"], help="Taichi backend (benchmarks/gpu.sh: cuda)")
    args = p.parse_args()
    over = {k.strip(): parse_value(v.strip(), k.strip()) for k, _, v in (item.partition("=") for item in args.set)}
    over["compare"] = "none"
    if args.kernels:
        init = ti.init
        ti.init = lambda *a, **kw: init(*a, **{**kw, "kernel_profiler": True})
    ti_dk.init(args.arch, args.threads)
    names = ("hybrid", "fv", "particle")
    scenes = {m: load_scene(args.scene, **over, method=m) for m in names}
    if args.whole:
        args.steps = scenes["hybrid"].n_steps
    args.particle_steps = min(args.particle_steps or args.steps, args.steps)
    if args.particle_steps < args.steps and any("dirichlet" in side for side in scenes["hybrid"].grid.boundary):
        print("note: Dirichlet sides: the particle method's count, and so its cost, changes in time")
    solvers, first = {}, {}
    for m in names:
        t = time.perf_counter()
        solvers[m] = make_solver(scenes[m], scenes[m].initial_ppc)
        ti.sync()
        first[m] = (time.perf_counter() - t, _timed(lambda: solvers[m].step(0)))
    t_first = dict(solvers["hybrid"].timing)
    n_walk = solvers["hybrid"].diagnostics()["particles"]  # after step 0
    solvers["walk"] = _plain_walk(scenes["hybrid"], n_walk)
    solvers["walk"].step(0)
    wall, kernels, mean_n, tenths = measure(solvers, args.steps, args.particle_steps,
                                            impl.get_runtime().prog if args.kernels else None)
    ms = {m: 1e3 * w / ((args.particle_steps if m in ("particle", "walk") else args.steps) - 1)
          for m, w in wall.items()}
    report(args, ms, kernels, mean_n, n_walk, solvers, first, t_first, tenths)


def report(args, ms, kernels, mean_n, n_walk, solvers, first, t_first, tenths) -> None:
    """The Markdown tables of :func:`main`."""
    steps = args.steps - 1
    n_particle = solvers["particle"].diagnostics()["mass"]
    walk_ms = ms["walk"] * mean_n / n_walk  # per particle, at the hybrid's mean count
    print(f"# {args.scene} {' '.join(args.set)}: {time.strftime('%Y-%m-%d %H:%M')}, {cpu_model()}, "
          f"{args.arch}, {args.threads} threads, steps 1-{steps} (particle method and plain walk 1-"
          f"{args.particle_steps - 1}, spread over those; step 0 apart), load average {os.getloadavg()[0]:.1f}\n")
    print("| | ms/step |\n|---|---|")
    print(f"| hybrid | {ms['hybrid']:.2f} |")
    for k, v in solvers["hybrid"].timing.items():
        print(f"| … {k} (HybridSolver.timing) | {1e3 * v / steps:.2f} |")
    if args.kernels:
        ktot = 1e3 * sum(kernels.values()) / steps
        print(f"| … kernel time, all tasks | {ktot:.2f} |")
        print(f"| … rest: launches, host work, syncs | {ms['hybrid'] - ktot:.2f} |")
    print(f"| fv step alone | {ms['fv']:.2f} |")
    print(f"| particle method alone ({n_particle / 1e6:.2f} M particles) | {ms['particle']:.2f} |")
    print(f"| plain walk of the hybrid's mean {mean_n / 1e3:.0f} k particles (uniform {n_walk / 1e3:.0f} k, "
          f"scaled) | {walk_ms:.2f} |")
    print(f"| … the particle method's per-particle cost × that count | {ms['particle'] * mean_n / n_particle:.2f} |")
    print(f"| **hybrid ÷ (fv + plain walk)** | **{ms['hybrid'] / (ms['fv'] + walk_ms):.2f}** |")
    print(f"| particle ÷ hybrid | {ms['particle'] / ms['hybrid']:.2f} |")
    print("\nfirst step (compilation, offline cache on), s: " + ", ".join(
        f"{m} build {b:.2f} + step 0 {s:.2f}" for m, (b, s) in first.items())
          + "; hybrid step 0 by part: " + ", ".join(f"{k} {v:.2f}" for k, v in t_first.items()))
    if args.whole:
        print("\n| tenth of the run | hybrid ms/step | its mean particles | particle ÷ hybrid |\n|---|---|---|---|")
        for k, (sec, cnt, m) in enumerate(tenths):
            if m:
                h = 1e3 * sec / m
                print(f"| {k + 1} | {h:.2f} | {cnt / m / 1e3:.0f} k | {ms['particle'] / h:.1f} |")
    if not args.kernels:
        return
    print("\n| hybrid kernel task | ms/step | share of step |\n|---|---|---|")
    for task, v in sorted(kernels.items(), key=lambda kv: -kv[1]):
        if 1e3 * v / steps > 0.005 * ms["hybrid"]:
            print(f"| {task} | {1e3 * v / steps:.3f} | {100 * 1e3 * v / steps / ms['hybrid']:.1f} % |")


if __name__ == "__main__":
    main()
