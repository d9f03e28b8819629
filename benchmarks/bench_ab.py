"""Two source trees in one process, stepped alternately: per-kernel time of each, same machine state.

    python benchmarks/bench_ab.py --before /path/to/old/tree [--scene sphere3d] [--steps 12] [--threads 2]
                                  [--set KEY=VALUE ...] [--start 0] [--check] [--blocks N [--clock cpu]]

On a shared VM whose speed drifts by 20-30 % between runs a minute apart (benchmarks/RESULTS.md),
before/after figures taken in separate processes cannot resolve a 10 % change. Here both trees'
``ti_dk`` packages are imported side by side (copied under the names ``ti_dk_before`` and
``ti_dk_after``: the package uses relative imports only), each builds the scene's solver in the
same Taichi program, and each step of the one is followed by the same step of the other. Printed:
the mean wall time of a step of each, and the mean time per step of every kernel task (Taichi's
kernel profiler) that takes more than 0.3 ms in either, with their ratio. ``--set`` takes scene
overrides as on the command line, ``--start`` untimed steps first, and ``--check`` says at the end
whether the two solvers' states are bit-identical (a change meant to keep the bits).
``--blocks N`` times blocks of ``--steps`` steps instead, the trees alternating block by block
(and which goes first), and prints each tree's best block: on a loaded host the best of many
short blocks is the steadier figure, and ``--clock cpu`` (the process's CPU time) steadier still
on one thread.
"""
import argparse
import importlib
import os
import shutil
import sys
import tempfile
import time


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", required=True, help="an older source tree (e.g. a git archive of main)")
    p.add_argument("--scene", default="sphere3d")
    p.add_argument("--steps", type=int, default=12)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene overrides, as on the CLI")
    p.add_argument("--start", type=int, default=0, help="steps taken (both trees, untimed) before the timed ones")
    p.add_argument("--check", action="store_true", help="at the end, say whether both solvers' states are bit-identical")
    p.add_argument("--blocks", type=int, default=0, help="best of this many alternating blocks of --steps steps")
    p.add_argument("--clock", choices=("wall", "cpu"), default="wall", help="with --blocks: wall or process CPU time")
    args = p.parse_args()
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    tmp = tempfile.mkdtemp()
    for name, tree in (("ti_dk_before", args.before), ("ti_dk_after", here)):
        shutil.copytree(os.path.join(tree, "ti_dk"), os.path.join(tmp, name))
    os.symlink(os.path.join(here, "scenes"), os.path.join(tmp, "scenes"))  # schema.scene_dir: a copy under another name has no <name>.scenes, so the folder next to it
    sys.path.insert(0, tmp)

    import taichi as ti
    from taichi.lang import impl
    names = ("ti_dk_before", "ti_dk_after")
    mods = {k: importlib.import_module(k) for k in names}
    init = ti.init
    ti.init = lambda *a, **kw: init(*a, **{**kw, "kernel_profiler": not args.blocks})
    mods["ti_dk_after"].init("cpu", args.threads)
    solvers = {}
    parse = mods["ti_dk_after"].scene.load.parse_value
    over = {k.strip(): parse(v.strip(), k.strip()) for k, _, v in (item.partition("=") for item in args.set)}
    for k, m in mods.items():
        sc = m.load_scene(args.scene, **over)
        moved = os.path.exists(os.path.join(tmp, k, "control", "registry.py"))  # an older tree: methods/registry.py
        registry = importlib.import_module(k + (".control" if moved else ".methods") + ".registry")
        solvers[k] = registry.make_solver(sc, sc.initial_ppc)
    for n in range(3 + args.start):  # compile, then the untimed start
        for s in solvers.values():
            s.step(n)
    if args.blocks:
        blocks(solvers, 3 + args.start, args)
        return
    wall = dict.fromkeys(names, 0.0)
    kernels: dict = {}
    prog = impl.get_runtime().prog
    first = 3 + args.start
    for n in range(first, first + args.steps):
        for k, s in solvers.items():
            ti.sync()
            ti.profiler.clear_kernel_profiler_info()
            t = time.perf_counter()
            s.step(n)
            ti.sync()
            wall[k] += time.perf_counter() - t
            prog.sync_kernel_profiler()
            prog.update_kernel_profiler()
            for r in prog.get_kernel_profiler_records():  # "<kernel>_c<id>_<n>_kernel_<task>_<kind>"
                task = r.name.split("_c")[0] + "_" + r.name.split("_kernel_")[-1]
                kernels[k, task] = kernels.get((k, task), 0.0) + r.kernel_time
    steps = args.steps
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, {args.scene}, {args.threads} threads, steps {first}-{first + steps - 1} "
          f"{' '.join(args.set)}, "
          f"before={os.path.abspath(args.before)}, after={here}")
    print("| | before | after | after/before |\n|---|---|---|---|")
    print(f"| step, ms | {1e3 * wall[names[0]] / steps:.1f} | {1e3 * wall[names[1]] / steps:.1f} | "
          f"{wall[names[1]] / wall[names[0]]:.3f} |")
    for task in sorted({t for _, t in kernels}):
        a, b = (kernels.get((k, task), 0.0) / steps for k in names)
        if max(a, b) > 0.3:
            print(f"| {task}, ms | {a:.2f} | {b:.2f} | {b / a if a else float('nan'):.3f} |")
    if args.check:
        import numpy as np
        a, b = (solvers[k].state() for k in names)
        diff = [k for k in a if k not in b or not np.array_equal(a[k], b[k])]
        print(f"\nstates after step {first + steps - 1}: " + ("bit-identical" if not diff else f"differ in {diff}"))


def blocks(solvers, first, args):
    """``--blocks``: each tree's best time a step over blocks of ``args.steps`` steps, alternating."""
    import taichi as ti
    clock = time.process_time if args.clock == "cpu" else time.perf_counter
    names = list(solvers)
    best = dict.fromkeys(names, float("inf"))
    n = first
    for b in range(args.blocks):
        for k in (names if b % 2 == 0 else names[::-1]):
            ti.sync()
            t = clock()
            for i in range(args.steps):
                solvers[k].step(n + i)
            ti.sync()
            best[k] = min(best[k], (clock() - t) / args.steps)
        n += args.steps
    a, b = (best[k] for k in names)
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, {args.scene}, {args.threads} threads, {' '.join(args.set)}, "
          f"best of {args.blocks} blocks of {args.steps} steps, {args.clock} clock, load {os.getloadavg()[0]:.1f}")
    print(f"| step, ms | before {1e3 * a:.3f} | after {1e3 * b:.3f} | after/before {b / a:.3f} |")


if __name__ == "__main__":
    main()
