"""The options of a run that are not scene keys (the command line's, :func:`ti_dk.run`'s, a Dask
run's), checked before anything starts: whole numbers in range, options that would silently undo
each other, a ``--restart`` checkpoint that fits the scene, an ``--out`` that can be written."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..core.errors import ConfigError
from ..scene.schema import MAX_MEMBERS, MAX_STEPS, Key, Scene
from .checkpoint import check_checkpoint_file


def check_options(scene: Scene, *, out: str | Path | None = None, executor: str = "local",
                  workers: int | None = None, chunk: int | None = None, threads: int | None = None,
                  scheduler: str | None = None, checkpoint_every: int = 0, restart: str | Path | None = None,
                  movie: bool = False, frames: bool | None = None, member0: int = 0) -> None:
    """Check the options of a run (the command line's, or :func:`ti_dk.run`'s) before anything starts;
    options that would silently undo each other are refused too."""
    def whole(name: str, value: Any, lo: int, hi: int | None = None) -> None:
        if value is None:
            return
        Key("int", "", lo=lo, hi=hi).check(name, value)

    if movie and frames is False:
        raise ConfigError("--movie is made of frames: drop --no-frames or --movie")
    if checkpoint_every and out is None:  # it would be dropped silently: a checkpoint is written into out
        raise ConfigError("checkpoint_every needs an output folder to write the checkpoint into: give out")
    whole("--threads", threads, 1, 4096)
    whole("--checkpoint-every", checkpoint_every, 0, MAX_STEPS)
    whole("--workers", workers, 1, 4 * (os.cpu_count() or 1) if scheduler is None else 100_000)
    whole("--chunk", chunk, 1, MAX_MEMBERS)
    whole("member0", member0, 0, MAX_MEMBERS - scene.method.ensemble)  # the last member's index fits 32 bits
    if executor == "dask":
        for flag, given in (("--checkpoint-every", checkpoint_every), ("--restart", restart), ("--movie", movie)):
            if given:
                raise ConfigError(f"{flag} is for the local executor: drop it or use --executor local "
                                  "(a stopped Dask run resumes from its finished chunks)")
    else:
        for flag, given in (("--workers", workers), ("--chunk", chunk), ("--scheduler", scheduler)):
            if given is not None:
                raise ConfigError(f"{flag} is for --executor dask: drop it or add --executor dask")
    for flag, path, check in (("--restart", restart, lambda p: _check_restart(p, scene)), ("--out", out, _check_out)):
        try:
            if path is not None:
                check(path)
        except OSError as exc:  # a name longer than the file system takes, a loop of links
            raise ConfigError(f"{flag}: {exc.strerror}; give a shorter, plain path") from None


def _check_restart(restart: str | Path, scene: Scene) -> None:
    """A checkpoint of this ti_dk's format, whole, for these settings (the full check of its content
    against the solvers comes when it is loaded)."""
    if not Path(restart).is_file():  # missing, or a folder, a FIFO (whose read would wait forever), a device
        raise ConfigError(f"--restart {restart}: no such checkpoint file (or not a regular file)")
    check_checkpoint_file(Path(restart), scene)


def _check_out(out: str | Path) -> None:
    """An output directory that exists or can be made, and can be written."""
    if str(out) == "":
        raise ConfigError("--out '': give a directory (. for the current one)")
    p = Path(out)
    parent = next((q for q in (p, *p.parents) if q.exists()), None)
    if parent is not None and not parent.is_dir():
        raise ConfigError(f"--out {out}: {parent} is a file: give a directory")
    if parent is not None and not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {out}: {parent} is not writable here; give a directory you can write")
