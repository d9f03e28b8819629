"""Stopping a run on a signal (:class:`~ti_dk.core.errors.Stopped`); no heavy import, so that the command
line can install its handlers before anything else (:func:`catch_early`)."""
from __future__ import annotations

import contextlib
import os
import signal
import threading
from pathlib import Path

from ..core.errors import Stopped

# set by the handlers of stop_on_signals(), read between steps; "at_once": end in the handler itself
_STOP: dict = {"signal": None, "at_once": False}


SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)  # the signals that stop a run cleanly


def _handler(signum, frame):
    if _STOP["signal"] is not None:  # asked twice: the run did not reach its next check
        _end_now(signum, "a second time: ended at once, without waiting for the current step (the run file, "
                         "if any, stays marked incomplete)")
    if _STOP["at_once"]:
        _end_now(signum, "before the run began")
    _STOP["signal"] = signum


def _end_now(signum: int, when: str) -> None:
    """Leave at once with one line, closing nothing (a run file stays marked incomplete, as it was
    created; a lock left behind is taken over by the next run), whatever the process was waiting
    for; not an exception, which a broad ``except`` could take for another error."""
    try:
        os.write(2, f"ti_dk: error: stopped by {signal.Signals(signum).name} {when}\n".encode())
    except OSError:  # stderr gone with its terminal (SIGHUP)
        pass
    os._exit(128 + signum)


@contextlib.contextmanager
def stop_at_once():
    """A signal in here ends the process from its handler (:func:`_end_now`), even in a read that
    waits forever; for what comes before a run writes anything (reading the scene and its files,
    starting Taichi), where nothing can be left half-written."""
    check_stop()
    before, _STOP["at_once"] = _STOP["at_once"], True
    try:
        yield
    finally:
        _STOP["at_once"] = before


def catch_early() -> None:
    """Install the handlers of :func:`stop_on_signals` at once, for the command line, before its
    imports (Taichi, h5py: seconds): a signal that arrives meanwhile stops it at the first check."""
    if threading.current_thread() is threading.main_thread():
        for s in SIGNALS:
            signal.signal(s, _handler)


@contextlib.contextmanager
def stop_on_signals():
    """SIGTERM, SIGINT and SIGHUP set a flag that the run checks between steps (and after Taichi's
    start and the kernels' compilation), instead of raising wherever Python happens to be; inside
    :func:`stop_at_once`, or for a second signal before that check, the handler ends the process
    itself, with one line (:func:`_end_now`). Handlers restored after. A signal caught since :func:`catch_early` is kept."""
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
