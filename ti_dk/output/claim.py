"""Where a run writes and how it takes its output: every path inside ``--out``, an exclusive lock,
and a result replaced only once the new one is whole.

A run never writes through a link, never replaces a file it did not write, and never writes over
a finished result: with one in place (``--overwrite``), its run file, frames, snapshots and movie
are written into a staging folder beside them (``.<stem>.partial``) and moved into place
(``rename``, which replaces a name and never follows it) only when the run has finished. A failed
or stopped replace thus leaves the old result, frames and snapshots as they were. With no finished
result in place, a run writes in place, so that a killed one leaves its incomplete file where it
is looked for.
"""
from __future__ import annotations

import fcntl
import os
import re
import shutil
import stat
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import h5py

from ..core.errors import ConfigError
from .files import is_complete, output_error

# what ti_dk writes inside its folders (a frame, S(k), a snapshot or one a killed run left half-written)
OURS_IN = {"frames": re.compile(r"frame_\d{4,}\.png|structure_factor\.png|series\.png|observables\.png"),
           "snapshots": re.compile(r"data\d{6}\.h5(\.\w+\.tmp)?")}


@dataclass(frozen=True)
class Outputs:
    """Every path a run writes, named once and all inside ``out``.

    ``run_file`` ``<out>/<name>_<method>.h5``, ``frames`` ``…_frames/``, ``snapshots``
    ``…_openpmd/``, ``movie`` ``….mp4`` (together: the result, :attr:`RESULT`), ``checkpoint``
    ``…_checkpoint.h5``, ``chunks`` ``…_chunks/`` (Dask), ``lock`` ``….lock`` (held while a run
    writes any of them) and ``stage`` ``.….partial/``, where the result is written before it takes
    its place (:meth:`staged`) when the run replaces a finished result (``staging``).
    """

    out: Path
    stem: str
    staging: bool = False  # the result is written in ``stage`` (a finished one is in place)

    @classmethod
    def of(cls, out: str | Path, scene) -> "Outputs":
        """The outputs of ``scene`` in directory ``out``: files named ``<scene>_<method>``."""
        if str(out) == "":
            raise ConfigError("--out '': give a directory (. for the current one)")
        return cls(Path(out), f"{scene.name}_{scene.method.name}")  # the name is a plain file name (load.py)

    run_file = property(lambda self: self.out / f"{self.stem}.h5")
    frames = property(lambda self: self.out / f"{self.stem}_frames")
    snapshots = property(lambda self: self.out / f"{self.stem}_openpmd")
    checkpoint = property(lambda self: self.out / f"{self.stem}_checkpoint.h5")
    chunks = property(lambda self: self.out / f"{self.stem}_chunks")
    lock = property(lambda self: self.out / f"{self.stem}.lock")
    movie = property(lambda self: self.out / f"{self.stem}.mp4")
    structure_factor = property(lambda self: self.frames / "structure_factor.png")  # S(k) drawn, beside the frames
    series = property(lambda self: self.frames / "series.png")  # the run's series over time (output/series.py)
    observables = property(lambda self: self.frames / "observables.png")  # its [observables] over time
    stage = property(lambda self: self.out / f".{self.stem}.partial")

    @property
    def result(self) -> tuple[Path, ...]:
        """What a run's result consists of, in the order it takes its place (the run file, which says
        whether the result is complete, last)."""
        return self.frames, self.snapshots, self.movie, self.run_file

    def staged(self, path: Path) -> Path:
        """Where the result's part ``path`` is written until the run ends."""
        return self.stage / path.name if self.staging else path

    def chunk(self, member0: int) -> Path:
        """The file of the finished chunk whose first member is ``member0`` (Dask)."""
        return self.chunks / f"chunk_{member0:09d}.h5"

    def chunk_files(self) -> list[Path]:
        """The finished chunks' files, in member order."""
        return sorted(self.chunks.glob("chunk_*.h5"))

    @contextmanager
    def claim(self, overwrite: bool = False, fresh: bool = True):
        """Hold the exclusive lock for the whole run; refuse a busy output, a complete result (without
        ``overwrite``) and anything at the output's paths that is not ti_dk's; yield the outputs to
        write, staged (:meth:`staged`) when a complete result is in place.

        A ``fresh`` run (not a restart) starts from an empty stage, or in place after removing the
        parts of an unfinished result; a restart continues the stage its run left, or the files in
        place. On the way out the stage takes the result's place after a finished run; after a
        failed or stopped one the old result stays whole and the stage stays for ``--restart``
        (if there is a checkpoint). The lock file is removed at the end.
        """
        fd = self._take_lock()
        finished, claimed = False, self
        try:
            self._refuse_foreign()
            complete = is_complete(self.run_file)
            if complete and not overwrite:
                raise ConfigError(f"{self.run_file} holds a complete result: add --overwrite to replace it, "
                                  "or give another --out")
            claimed = replace(self, staging=complete)
            claimed._prepare(fresh)
            yield claimed
            finished = True
        except OSError as exc:
            raise output_error(self.out, exc) from None
        finally:
            try:
                claimed._settle(finished)
            finally:
                self._drop_lock(fd)

    def _take_lock(self) -> int:
        """Lock ``lock`` (created if absent, never through a link); say so when an earlier run left it."""
        if self.lock.is_symlink():
            raise ConfigError(f"{self.lock} is a symbolic link: ti_dk never writes through links; remove it or "
                              "give another --out")
        _regular(self.lock)
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise output_error(self.out, exc) from None
        while True:
            try:
                fd = os.open(self.lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                raise output_error(self.lock, exc) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
                os.close(fd)
                raise ConfigError(f"{self.run_file} is being written by another run (pid {pid}): wait for it to "
                                  "finish or give another --out") from None
            try:
                if os.stat(self.lock).st_ino == os.fstat(fd).st_ino:
                    break
            except FileNotFoundError:
                pass
            os.close(fd)  # its holder removed it between our open and our lock: take the new one
        try:
            left = os.pread(fd, 64, 0).decode(errors="replace").strip()
            if not left.isdigit() and left:  # never a pid that ti_dk wrote: the user's file, left as it was
                os.close(fd)
                raise _foreign(self.lock)
            if left:
                print(f"ti_dk: note: {self.lock} was left by run pid {left}, which ended without removing it "
                      "(a stale lock, no run holds it): taking it over", file=sys.stderr)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as exc:  # the disk is full
            self._drop_lock(fd)
            raise output_error(self.lock, exc) from None
        return fd

    def _drop_lock(self, fd: int) -> None:
        """Remove the lock file while holding it, then release it (a run that opened the old file
        before the removal sees that it is gone and takes a new one)."""
        try:
            os.unlink(self.lock)
        except OSError:
            pass
        os.close(fd)

    def _refuse_foreign(self) -> None:
        """Refuse links, and anything at the output's paths that ti_dk cannot tell it wrote: it removes
        or replaces only its own run file, checkpoint, lock, frames, snapshots, stage and a movie its
        run file records (:meth:`_refuse_foreign_parts`)."""
        for p in (*self.result, self.checkpoint, self.chunks, self.stage):
            if p.is_symlink():
                raise ConfigError(f"{p} is a symbolic link: ti_dk never writes through links; remove it or give "
                                  "another --out")
        for p, folder in ((self.frames, True), (self.snapshots, True), (self.chunks, True), (self.stage, True),
                          (self.movie, False), (self.checkpoint, False), (self.run_file, False)):
            if p.exists() and p.is_dir() != folder:
                raise ConfigError(f"{p} is a {'file' if folder else 'folder'} that ti_dk did not write: move it "
                                  "away or give another --out")
        self._refuse_foreign_parts()
        _regular(self.checkpoint)
        if self.checkpoint.exists() and not _h5_attrs(self.checkpoint, ("scene", "step")):
            raise ConfigError(f"{self.checkpoint} is not a ti_dk checkpoint: move it away or give another --out")
        self._refuse_foreign_in_stage()

    def _refuse_foreign_in_stage(self) -> None:
        """Refuse a stage that holds anything but a staged result of ti_dk's."""
        if self.stage.is_dir():
            for p in self.stage.iterdir():
                if p.name not in {q.name for q in self.result}:
                    raise _foreign(p)
            replace(self, staging=True)._refuse_foreign_parts()

    def _refuse_foreign_parts(self) -> None:
        """Refuse a result (in place, or staged) with a part ti_dk cannot tell it wrote: a run file
        that is not one, a movie its run file does not record (``movie_bytes``), anything in the
        frames or snapshots folders but ti_dk's files."""
        run_file, movie = self.staged(self.run_file), self.staged(self.movie)
        for part in (run_file, movie):
            _regular(part)
        attrs = _h5_attrs(run_file, ("scene", "versions", "complete")) if run_file.exists() else {}
        if attrs is None:
            raise ConfigError(f"{run_file} is not a ti_dk run file: move it away or give another --out")
        if movie.exists() and attrs.get("movie_bytes") != movie.stat().st_size:
            raise ConfigError(f"{movie} was not written by ti_dk (its run file records no such movie): move it "
                              "away or give another --out")
        for part, name in ((self.frames, "frames"), (self.snapshots, "snapshots")):
            folder = self.staged(part)
            for p in folder.iterdir() if folder.is_dir() else ():
                if not OURS_IN[name].fullmatch(p.name) or (p.is_dir() and not p.is_symlink()):
                    raise _foreign(p)

    def _prepare(self, fresh: bool) -> None:
        """For a fresh run, no stage left by an earlier one and, in place, no part of an unfinished
        result (a series never mixes two runs); for a staged one, its stage (a restart's kept one)."""
        if fresh and self.stage.exists():
            shutil.rmtree(self.stage)
        if self.staging:
            self.stage.mkdir(exist_ok=True)
        elif fresh:
            for part in self.result:
                if part.is_dir():
                    shutil.rmtree(part)
                else:
                    part.unlink(missing_ok=True)

    def _settle(self, finished: bool) -> None:
        """The stage takes the result's place, or stays (see :meth:`claim`)."""
        if not self.staging or not self.stage.is_dir():
            return
        try:
            if finished:
                self._swap()
            elif not self.checkpoint.exists() or not self.staged(self.run_file).exists():
                try:
                    self._refuse_foreign_in_stage()
                except ConfigError:  # something of the user's was put in it during the run: it stays
                    return
                shutil.rmtree(self.stage, ignore_errors=True)
        except OSError as exc:
            raise output_error(self.out, exc) from None

    def _swap(self) -> None:
        """Move the old result aside, the staged one into place (each a rename), then drop the old."""
        replace(self, staging=False)._refuse_foreign_parts()  # nothing of the user's came in meanwhile
        old = Path(tempfile.mkdtemp(prefix=f".{self.stem}.old.", dir=self.out))
        try:
            for final in self.result:
                if os.path.lexists(final):
                    os.rename(final, old / final.name)
                if os.path.lexists(self.staged(final)):
                    os.rename(self.staged(final), final)
        finally:
            shutil.rmtree(old, ignore_errors=True)
        try:
            self.stage.rmdir()  # empty, unless something of the user's was put in it during the run
        except OSError:
            pass


def _foreign(path: Path) -> ConfigError:
    return ConfigError(f"{path} was not written by ti_dk: move it away or give another --out")


def _regular(path: Path) -> None:
    """Refuse something at ``path`` that is not a regular file (a FIFO, a device: a read would wait
    forever); links are refused apart, and nothing at all is fine."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode) and not stat.S_ISLNK(mode) and not stat.S_ISDIR(mode):
        raise ConfigError(f"{path} is not a regular file (a FIFO or a device): ti_dk writes only files it made; "
                          "move it away or give another --out")


def _h5_attrs(path: Path, needed: tuple[str, ...]) -> dict | None:
    """The root attributes of an HDF5 file of ti_dk's that has all of ``needed``, or None."""
    try:
        with h5py.File(path, "r", locking=False) as f:
            return dict(f.attrs) if all(k in f.attrs for k in needed) else None
    except (OSError, ValueError):
        return None
