"""Stopping a run on a signal, and the errors a run ends with; no heavy import, so that the command
line can install its handlers before anything else (:func:`catch_early`)."""
from __future__ import annotations

import contextlib
import os
import signal
import threading
from pathlib import Path


class SimulationError(RuntimeError):
    """The run went wrong in a way the user can fix (unstable scheme, too many particles)."""


class Stopped(SimulationError):
    """SIGTERM or SIGINT arrived: the run stopped between two steps, its output closed and marked
    incomplete. ``status``: the exit status a shell gives for that signal (143, 130)."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status  # 128 + the signal's number


_STOP: dict = {"signal": None}  # set by the handlers of stop_on_signals(), read between steps


SIGNALS = (signal.SIGTERM, signal.SIGINT)  # the signals that stop a run cleanly


def _handler(signum, frame):
    if _STOP["signal"] is not None:  # asked twice: stop at once, the default way
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
    _STOP["signal"] = signum


def catch_early() -> None:
    """Install the handlers of :func:`stop_on_signals` at once, for the command line, before its
    imports (Taichi, h5py: seconds): a signal that arrives meanwhile stops it at the first check."""
    if threading.current_thread() is threading.main_thread():
        for s in SIGNALS:
            signal.signal(s, _handler)


@contextlib.contextmanager
def stop_on_signals():
    """SIGTERM and SIGINT set a flag that the run checks between steps (and after Taichi's start and
    the kernels' compilation), instead of raising wherever Python happens to be; handlers restored after.
    A signal caught since :func:`catch_early` is kept."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, _handler) for s in SIGNALS}
    if not all(h is _handler for h in old.values()):
        _STOP["signal"] = None
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        _STOP["signal"] = None


def check_stop(where: str = " before the first step", run_file: Path | None = None,
               checkpoint: Path | None = None) -> None:
    """Raise :class:`Stopped` if a signal arrived; the message names the run file, which the caller
    closes marked incomplete, and the latest checkpoint, only if there is one."""
    signum = _STOP["signal"]
    if signum is None:
        return
    name = signal.Signals(signum).name
    msg = f"stopped by {name}{where}"
    msg += f"; {run_file} is marked incomplete" if run_file is not None else ""
    msg += f"; resume with --restart {checkpoint}" if checkpoint is not None else ""
    raise Stopped(msg, 128 + signum)
