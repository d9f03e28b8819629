"""Ensembles split into chunks of members, run on Dask workers and merged exactly.

Every random number is keyed on a member's *global* index, so a member's realisation does not
depend on which chunk or worker ran it; the driver merges the chunks' moment accumulators
(Pébay) in member order, so any chunking gives the single-process statistics to round-off.
Finished chunks are kept in ``<out>/<scene>_<method>_chunks/`` (written atomically), so a run
stopped after k of n chunks resumes with the rest; a chunk whose worker died is retried by Dask
and counted once.
"""
import math
import os
import sys
import time
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from . import controller, runtime, signals
from .options import check_options
from ..core.errors import ConfigError
from ..scene.schema import Scene
from ..output.claim import Outputs
from ..output.files import (RunFile, atomic_h5, output_error, read_group, read_rows, same_scene, scene_json, write_group,
                 write_rows)
from ..core.stats import CellStats

EXECUTORS = ("local", "dask")


def chunks(ensemble: int, size: int) -> list[tuple[int, int]]:
    """``(member0, count)`` of consecutive chunks of at most ``size`` members."""
    return [(m, min(size, ensemble - m)) for m in range(0, ensemble, size)]


def run_chunk(scene: Scene, member0: int, threads: int | None = None) -> dict:
    """Run members ``member0 … member0 + scene.method.ensemble − 1`` (in a worker process)."""
    try:  # tell the driver this chunk started here (a second start means a retry)
        from distributed import Queue

        Queue("ti_dk-attempts").put((member0, os.getpid()))
    except (ImportError, ValueError, RuntimeError):  # not on a Dask worker
        pass
    # Not a fresh runtime per chunk, though a chunk's solver then compiles anew (its fields get new
    # ids, on which the offline cache is keyed): a reset dumps the offline cache, and a worker
    # killed while dumping leaves its lock behind, after which every process on that cache
    # compiles everything and warns (measured: tests/control/test_ensemble.py's killed worker).
    if not runtime.started_by_this_thread():  # Taichi breaks when started in another thread (an
        runtime.init("cpu", threads)  # unguarded ti_dk.init in a script Dask re-imports): start it here
    res = controller.run(scene, progress=False, member0=member0)
    return {"member0": member0, "times": res.times, "rows": res.rows, "diagnostics": res.diagnostics,
            "series": res.series, "final_density": res.final_density, "wall_time": res.wall_time}


def run(scene: Scene, executor: str = "local", out: str | Path | None = None, progress: bool | None = None,
        chunk: int | None = None, workers: int = 2, threads: int = 1, scheduler: str | None = None,
        overwrite: bool = False) -> runtime.Result:
    """Run ``scene`` in-process (``local``: the batched ensemble) or in chunks on Dask.

    ``chunk``: members per chunk (default: the ensemble over 4 × workers for members under 4096
    cells, over the workers for larger ones); ``workers`` and
    ``threads`` size the LocalCluster started on this machine unless ``scheduler`` (an address
    such as ``tcp://host:8786``, e.g. from dask-jobqueue) names an existing cluster. The output
    is claimed as :func:`ti_dk.run` claims it (one run at a time, ``overwrite`` to replace a
    complete result); a signal seen by :func:`ti_dk.control.signals.stop_on_signals` stops it between chunks.
    """
    if executor not in EXECUTORS:
        raise ConfigError(f"executor '{executor}': use one of {', '.join(EXECUTORS)}")
    if executor == "local":
        return controller.run(scene, out=out, progress=progress, overwrite=overwrite)
    check_options(scene, executor="dask", chunk=chunk, workers=workers, threads=threads, scheduler=scheduler)
    if out is None:
        return _run_dask(scene, None, progress, chunk, workers, threads, scheduler)
    outputs = Outputs.of(out, scene)
    with outputs.claim(overwrite) as outputs:
        try:
            return _run_dask(scene, outputs, progress, chunk, workers, threads, scheduler)
        except OSError as exc:
            raise output_error(outputs.out, exc) from None


def _run_dask(scene: Scene, outputs: Outputs | None, progress, chunk, workers, threads, scheduler) -> runtime.Result:
    try:
        from distributed import Client, LocalCluster, Queue
    except ImportError:
        raise ConfigError("the dask executor needs Dask: pip install -e '.[dask]'") from None
    if scene.grid.dim > 1 and scene.method.ensemble == 1:
        raise ConfigError("one member cannot be split into chunks: use --executor local")
    wall0 = time.perf_counter()
    # small members: 4 chunks per worker (finer retries and resume); large ones: 1, since every
    # chunk pays its own JIT and per-step launches (RESULTS: 4x slower for 2-member chunks of 64²)
    per_worker = 4 if math.prod(scene.grid.cells) < 4096 else 1
    size = chunk or max(1, math.ceil(scene.method.ensemble / (per_worker * workers)))
    todo = chunks(scene.method.ensemble, size)
    done = _load_chunks(outputs, scene) if outputs is not None else {}
    show = sys.stderr.isatty() if progress is None else progress
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    client = Client(scheduler or cluster)
    attempts: dict[int, int] = {}
    try:
        queue = Queue("ti_dk-attempts", client=client)
        futures = [client.submit(run_chunk, scene.replace(ensemble=n), m0, threads, pure=False,
                                 retries=3, key=f"ti_dk-chunk-{m0}-{time.time_ns()}")
                   for m0, n in todo if m0 not in done]
        with tqdm(total=scene.method.ensemble, initial=sum(n for m0, n in todo if m0 in done), unit="member",
                  desc=f"{scene.name}/{scene.method.name} on dask", disable=not show, file=sys.stderr) as bar:
            for fut in _finished(futures):
                r = fut.result()
                if r["member0"] not in done:  # a chunk is counted once, however often it ran
                    done[r["member0"]] = r
                    if outputs is not None:
                        _save_chunk(outputs, scene, r)
                    bar.update(len(r["final_density"]))
        while queue.qsize():
            m0, _ = queue.get()
            attempts[m0] = attempts.get(m0, 0) + 1
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return _merge(scene, [done[m0] for m0, _ in todo], outputs, time.perf_counter() - wall0,
                  {"chunks": len(todo), "chunk_size": size, "retried": sorted(m for m, k in attempts.items() if k > 1)})


def _finished(futures):
    """The futures as they finish, looking for a stop signal twice a second (finished chunks are kept)."""
    from distributed import wait

    pending = set(futures)
    while pending:
        signals.check_stop(f" with {len(pending)} chunk(s) to go (the finished ones are kept for the next run)")
        try:
            done, pending = wait(pending, timeout=0.5, return_when="FIRST_COMPLETED")
        except TimeoutError:
            continue
        yield from done


def _merge(scene: Scene, parts: list[dict], outputs: Outputs | None, wall: float, info: dict) -> runtime.Result:
    """Merge the chunks' accumulators in member order; per-step diagnostics are summed over members
    (``min_density`` is the minimum)."""
    hist = scene.stats.histogram
    rows = []
    for i in range(len(parts[0]["rows"])):
        cs = CellStats(scene.grid.cells, scene.grid.cell_volume, hist, scene.stats.structure_factor)
        for p in parts:
            cs.merge_row(p["rows"][i])
        rows.append(cs.row())
    diag = {}
    for k in parts[0]["diagnostics"]:
        v = np.stack([p["diagnostics"][k] for p in parts])
        diag[k] = v[0] if k == "time" else v.min(axis=0) if k == "min_density" else v.sum(axis=0)
    times = parts[0]["times"]
    series = {k: v if k == "time" else np.concatenate([p["series"][k] for p in parts], axis=1)  # members side by side
              for k, v in parts[0]["series"].items()}
    path = None
    if outputs is not None:  # the run file as a single-process run writes it
        rf = RunFile.of(outputs, scene)
        rf.write_rows(times, rows)
        rf.write_diagnostics({k: list(v) for k, v in diag.items()})
        rf.write_series(series, tuple(name for name, _ in scene.stats.observables))
        rf.annotate("chunks", info)
        rf.close(wall)
        path = rf.path
    return runtime.Result(scene=scene, times=times, cell_volume=scene.grid.cell_volume,
                          stats=runtime.stats_of(rows, hist), diagnostics=diag,
                          final_density=np.concatenate([p["final_density"] for p in parts]),
                          wall_time=wall, path=path, timing={"total": wall}, rows=rows, series=series, chunks=info)


def _save_chunk(outputs: Outputs, scene: Scene, r: dict) -> None:
    outputs.chunks.mkdir(parents=True, exist_ok=True)
    with atomic_h5(outputs.chunk(r["member0"])) as f:
        f.attrs["scene"] = scene_json(scene)
        f.attrs["member0"], f.attrs["wall_time"] = r["member0"], r["wall_time"]
        f["times"], f["final_density"] = r["times"], r["final_density"]
        write_rows(f, r["rows"])
        write_group(f, "diagnostics", r["diagnostics"])
        write_group(f, "series", r["series"])


def _load_chunks(outputs: Outputs, scene: Scene) -> dict[int, dict]:
    """Chunks a stopped run already finished (for this very scene); an unreadable one is run again."""
    done = {}
    for path in outputs.chunk_files():
        try:
            with h5py.File(path, "r") as f:
                if not same_scene(f, scene):
                    raise ConfigError(f"{outputs.chunks} holds chunks of other scene settings: remove it or use another --out")
                done[int(f.attrs["member0"])] = {
                    "member0": int(f.attrs["member0"]), "times": f["times"][()],
                    "final_density": f["final_density"][()], "rows": read_rows(f),
                    "diagnostics": read_group(f["diagnostics"]), "series": read_group(f["series"]),
                    "wall_time": float(f.attrs["wall_time"])}
        except (OSError, KeyError) as exc:
            print(f"ti_dk: warning: {path} is unreadable ({str(exc).splitlines()[0]}); running that chunk again",
                  file=sys.stderr)
    return done
