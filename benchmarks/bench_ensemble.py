"""Ensemble throughput: the in-process batched ensemble against Dask chunks, by worker count.

    python benchmarks/bench_ensemble.py

Member-steps per second (members × steps / wall time of the whole run, cluster start and JIT in
the workers included) for a small member (void1d, 100 cells) and a large one (ellipse2d fv, 64²).
"""
import time

import ti_dk
from ti_dk import load_scene
from ti_dk.control import ensemble


def rate(scene, executor, **kw):
    t = time.perf_counter()
    ensemble.run(scene, executor, progress=False, **kw)
    return scene.method.ensemble * scene.n_steps / (time.perf_counter() - t)


def main():
    ti_dk.init("cpu")
    cases = {"void1d fv, 100 cells, 4000 members": load_scene("void1d", ensemble=4000, t_end=0.0025),
             "ellipse2d fv, 64², 16 members": load_scene("ellipse2d", method="fv", compare="none", cells=[64, 64],
                                                        ensemble=16, t_end=0.0024)}
    print("| case | executor | member-steps/s |\n|---|---|---|")
    for name, scene in cases.items():
        rate(scene, "local")  # JIT into the offline cache first
        print(f"| {name} | local (in-process, 2 threads) | {rate(scene, 'local'):,.0f} |")
        for workers in (1, 2):
            print(f"| {name} | dask, {workers} worker(s) × 1 thread | "
                  f"{rate(scene, 'dask', workers=workers, threads=1):,.0f} |")


if __name__ == "__main__":
    main()
