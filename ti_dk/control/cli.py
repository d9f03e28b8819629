"""``python -m ti_dk.scene NAME|PATH``: run a scene from the command line.

Exit status: 0 done; 2 bad input (one line saying what to change; nothing written); 1 the run
failed (I/O error, unstable scheme; the output is marked incomplete); 130/143 stopped by SIGINT or
SIGTERM (output closed and marked incomplete).
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings

from ..core.errors import ConfigError, OutputError, SimulationError, Stopped
from ..scene import checks, estimates, load, schema
from . import controller, ensemble, runtime, signals
from .options import check_options


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block), as every other input error."""

    def error(self, message: str):
        """Leave with one line and exit status 2."""
        sys.exit(_fail(f"{message}: see {self.prog} --help"))


class Help(argparse.RawDescriptionHelpFormatter):
    """Defaults shown where there is one, and only once."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default not in (None, False, [], argparse.SUPPRESS) and "default" not in text:
            text += " (default: %(default)s)"
        return text


def parser(prog: str, doc: str, out: str, ensemble: str = "number of independent members") -> Parser:
    """A command line on a scene: the scene, ``--ensemble``, ``--seed``, ``--t-end``, ``--set``,
    ``--out`` (default ``out``: what it holds), ``--arch``, ``--threads``, ``--no-progress``."""
    p = Parser(prog=prog, description=doc, formatter_class=Help,
               epilog="scene keys, for --set KEY=VALUE (or the scene's TOML file):\n" + schema.keys_help())
    p.add_argument("scene", help=f"scene name ({', '.join(load.available_scenes())}) or a .toml path")
    p.add_argument("--ensemble", type=int, help=ensemble)
    p.add_argument("--seed", type=int, help="random seed in [0, 2^64 - 1] (same seed, same result on any thread count)")
    p.add_argument("--t-end", type=float, help="end time")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any scene key (list below), e.g. --set C=0.05 --set cells=[64,64]")
    p.add_argument("--out", default="renders", help=out)
    p.add_argument("--arch", default="cpu", help="Taichi backend: cpu or cuda")
    p.add_argument("--threads", type=int, help="CPU threads (default: all cores)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line ``argv`` (default ``sys.argv[1:]``) parsed: :func:`parser`'s arguments and
    the run's own (``--method``, ``--quick``, frames, snapshots, checkpoints, the executor)."""
    p = parser("python -m ti_dk.scene", __doc__, "output directory for <scene>_<method>.h5 and the rest")
    p.add_argument("--method", help="override the scene's method (" + ", ".join(schema.METHODS) + ")")
    p.add_argument("--overwrite", action="store_true", help="replace a complete result already in --out")
    p.add_argument("--quick", action="store_true",
                   help="a seconds-long preview: a quarter of the cells per axis, a stable C, files <scene>_quick_*")
    p.add_argument("--no-frames", action="store_true", help="write no PNG frames (2D/3D scenes)")
    p.add_argument("--movie", action="store_true",
                   help="also write movie_frames evenly spaced frames and <scene>_<method>.mp4 beside the run file")
    p.add_argument("--no-snapshots", action="store_true", help="write no openPMD snapshots (2D/3D scenes)")
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="K",
                   help="write <scene>_<method>_checkpoint.h5 every K steps (default: never)")
    p.add_argument("--restart", metavar="FILE", help="continue from a checkpoint written by --checkpoint-every")
    p.add_argument("--executor", choices=ensemble.EXECUTORS, default="local",
                   help="local: the batched ensemble in this process; dask: chunks of members on Dask workers")
    p.add_argument("--workers", type=int, help="dask: worker processes of the local cluster (default: 2)")
    p.add_argument("--chunk", type=int, help="dask: members per chunk (default: ensemble / (4 workers))")
    p.add_argument("--scheduler", help="dask: address of an existing cluster instead of a local one")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """``python -m ti_dk.scene``: run the scene ``argv`` names; returns the exit status (module
    docstring)."""
    return guarded(lambda: parse_args(argv), _run)


def guarded(parse, body) -> int:
    """``body(parse())`` under the stop signals, its errors as one line and an exit status (module
    docstring)."""
    with signals.stop_on_signals():  # first: a signal from here on stops the run with one line
        try:
            args = parse()
            signals.check_stop()
            return body(args)
        except ConfigError as exc:
            return _fail(str(exc))
        except Stopped as exc:
            return _fail(str(exc), exc.status)
        except OutputError as exc:
            _fail(str(exc), 1)
            _exit_now(1)
        except SimulationError as exc:
            return _fail(str(exc), 1)


def _run(args: argparse.Namespace) -> int:
    """The run the parsed command line asks for; its summary on stdout."""
    with signals.stop_at_once():  # nothing written yet: a signal ends even a read that waits
        scene = _prepare(args)
    # Taichi's start outside stop_at_once: a process ended at once (os._exit) while ti.init holds the
    # kernel cache's lock file leaves it behind, and every later run warns "Lock ... ticache.lock failed"
    signals.check_stop()
    runtime.init(args.arch, args.threads)
    signals.check_stop()
    _announce(scene)
    if args.executor == "dask":
        result = ensemble.run(scene, "dask", out=args.out, progress=not args.no_progress, chunk=args.chunk,
                              workers=args.workers or 2, threads=args.threads or 1,
                              scheduler=args.scheduler, overwrite=args.overwrite)
    else:
        result = controller.run(scene, out=args.out, progress=not args.no_progress, frames=not args.no_frames,
                                movie=args.movie, snapshots=not args.no_snapshots, overwrite=args.overwrite,
                                checkpoint_every=args.checkpoint_every, restart=args.restart)
    print(controller.summary(result))
    return 0


def _prepare(args: argparse.Namespace) -> schema.Scene:
    """The scene the command line asks for, its options checked."""
    scene, caught, note = scene_of(args)
    check_options(scene, out=args.out, executor=args.executor, workers=args.workers,
                  chunk=args.chunk, threads=args.threads, scheduler=args.scheduler,
                  checkpoint_every=args.checkpoint_every, restart=args.restart, movie=args.movie,
                  frames=not args.no_frames)
    warn(caught)
    if note:
        print(f"ti_dk: {note}", file=sys.stderr)
    return scene


def scene_of(args: argparse.Namespace) -> tuple[schema.Scene, list[str], str]:
    """The scene the command line names with its overrides (``--set`` and the flags), the
    warnings its loading gave (for :func:`warn`, once the options are checked too), and the line
    :func:`quick_scene` says about its C ("" without ``--quick``)."""
    overrides = load.command_overrides(args.set, {k: getattr(args, k, None) for k in load.FLAGS})
    quick, note = getattr(args, "quick", False), ""
    if quick and "cells" in overrides:
        raise ConfigError("--quick sets the cells (a quarter per axis): drop it or --set cells")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", schema.ClampWarning)
        warnings.simplefilter("always", load.InputWarning)
        scene = load.load_scene(args.scene, **overrides)
        if quick:
            scene, note = quick_scene(args.scene, overrides, scene)
    return scene, [str(w.message) for w in caught], note


def quick_scene(scene_arg: str, overrides: dict, scene: schema.Scene) -> tuple[schema.Scene, str]:
    """``--quick``: ``scene`` (loaded from ``scene_arg`` with ``overrides``) on a quarter of its cells
    per axis (at least 8), named ``<name>_quick`` so that its files never block the full run's;
    where the scene's C is beyond the explicit stability limit on that coarser grid (a potential's
    drift grows with the cell size), half the limit instead. Returns the scene and a line saying
    which C it took and why ("" where it kept the scene's)."""
    cells = [max(8, n // 4) for n in scene.grid.cells]
    quick = dict(overrides, cells=cells, name=f"{scene.name}_quick")
    with warnings.catch_warnings():  # the coarse grid at the scene's C, only to read its limit: no clamp warning
        warnings.simplefilter("ignore")
        limit = checks.stability_limit(scene.replace(cells=tuple(cells), allow_unstable=True))  # replace checks C
    note = ""
    if scene.time.C >= limit and not scene.time.allow_unstable and scene.method.name != "particle":
        quick["C"] = float(f"{limit / 2:.2g}")
        note = (f"--quick: C = {quick['C']:g}, half the stability limit {limit:.3g} on {'x'.join(map(str, cells))} "
                f"cells (the scene's C = {scene.time.C:g} is beyond it)")
    return load.load_scene(scene_arg, **quick), note


def warn(messages: list[str]) -> None:
    """Each warning once, on one line (--quick loads twice)."""
    for message in dict.fromkeys(messages):
        print(f"ti_dk: warning: {_short(message)}", file=sys.stderr)


LONG_RUN = 60.0  # seconds: runs estimated to take longer say so before they start


def _announce(scene: schema.Scene) -> None:
    """Say how many steps a long run takes and roughly how long, before it starts."""
    steps, seconds = estimates.work_estimate(scene)
    if seconds > LONG_RUN:
        when = f"{seconds / 3600:.3g} h" if seconds > 3600 else f"{seconds / 60:.3g} min"
        print(f"ti_dk: {steps:,} steps of dt = {scene.dt:.4g} for {scene.method.ensemble:,} member(s) of "
              f"{'x'.join(map(str, scene.grid.cells))} cells: about {when} on 2 CPU cores (a rough estimate)",
              file=sys.stderr)


def _exit_now(status: int):
    """Leave at once after an I/O failure: an HDF5 file that could not be flushed (a full disk) can
    crash the interpreter when it is released at exit, so nothing more is released."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def _fail(message: str, status: int = 2) -> int:
    print(f"ti_dk: error: {_short(message)}", file=sys.stderr)
    return status


def _short(message: str, longest: int = 200) -> str:
    """``message`` on one line, each word longer than ``longest`` characters (a value of thousands
    of digits, a path thousands long) cut in its middle."""
    words = " ".join(message.splitlines()).split(" ")
    return " ".join(w if len(w) <= longest else f"{w[:longest // 2]}…{w[-20:]}" for w in words)

