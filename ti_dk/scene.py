"""``python -m ti_dk.scene NAME|PATH``: run a scene from the command line.

Bad input exits with status 2 and one line saying what to change; no file is written.
"""
from __future__ import annotations

import argparse
import signal
import sys
import warnings

from . import config, ensemble, sim


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m ti_dk.scene", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("scene", help=f"scene name ({', '.join(config.available_scenes())}) or a .toml path")
    p.add_argument("--method", choices=config.METHODS, help="override the scene's method")
    p.add_argument("--ensemble", type=int, help="number of independent members")
    p.add_argument("--seed", type=int, help="random seed (same seed, same result on any thread count)")
    p.add_argument("--t-end", type=float, help="end time")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any scene key, e.g. --set C=0.05 --set cells=[64,64]")
    p.add_argument("--out", default="renders", help="output directory for <scene>_<method>.h5")
    p.add_argument("--arch", default="cpu", help="Taichi backend: cpu or cuda")
    p.add_argument("--threads", type=int, help="CPU threads (default: all cores)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--quick", action="store_true", help="a seconds-long preview: a quarter of the cells per axis")
    p.add_argument("--no-frames", action="store_true", help="write no PNG frames (2D/3D scenes)")
    p.add_argument("--movie", action="store_true",
                   help="also write movie_frames evenly spaced frames and <scene>_<method>.mp4 beside the run file")
    p.add_argument("--no-snapshots", action="store_true", help="write no openPMD snapshots (2D/3D scenes)")
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="K",
                   help="write <scene>_<method>_checkpoint.h5 every K steps (0: never)")
    p.add_argument("--restart", metavar="FILE", help="continue from a checkpoint written by --checkpoint-every")
    p.add_argument("--executor", choices=ensemble.EXECUTORS, default="local",
                   help="local: the batched ensemble in this process; dask: chunks of members on Dask workers")
    p.add_argument("--workers", type=int, default=2, help="dask: worker processes of the local cluster")
    p.add_argument("--chunk", type=int, help="dask: members per chunk (default: ensemble / (4 workers))")
    p.add_argument("--scheduler", help="dask: address of an existing cluster instead of a local one")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    overrides = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep or not key:
            return _fail(f"--set {item!r}: write KEY=VALUE, e.g. --set C=0.05")
        overrides[key.strip()] = config.parse_value(value.strip())
    for key in ("method", "ensemble", "seed", "t_end"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
    if args.checkpoint_every < 0:
        return _fail(f"--checkpoint-every {args.checkpoint_every}: give a number of steps >= 0")
    signal.signal(signal.SIGTERM, _terminate)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", config.ClampWarning)
            scene = config.load_scene(args.scene, **overrides)
            if args.quick and "cells" not in overrides:
                scene = config.load_scene(args.scene, **overrides, cells=[max(8, n // 4) for n in scene.cells])
        for w in caught:
            print(f"ti_dk: warning: {w.message}", file=sys.stderr)
        sim.init(args.arch, args.threads)
        if args.executor == "dask":
            result = ensemble.run(scene, "dask", out=args.out, progress=not args.no_progress, chunk=args.chunk,
                                  workers=args.workers, threads=args.threads or 1, scheduler=args.scheduler)
        else:
            result = sim.run(scene, out=args.out, progress=not args.no_progress, frames=not args.no_frames,
                             movie=args.movie, snapshots=not args.no_snapshots,
                             checkpoint_every=args.checkpoint_every, restart=args.restart)
    except (config.ConfigError, sim.SimulationError) as exc:
        return _fail(str(exc))
    except Terminated:
        ckpt = " (resume with --restart and the latest checkpoint)" if args.checkpoint_every else ""
        return _fail(f"stopped by SIGTERM; the output file is marked incomplete{ckpt}", 143)
    print(sim.summary(result))
    return 0


class Terminated(Exception):
    """SIGTERM arrived: unwind so the output file is closed and marked incomplete."""


def _terminate(signum, frame):
    raise Terminated("stopped by SIGTERM")


def _fail(message: str, status: int = 2) -> int:
    print(f"ti_dk: error: {message}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
