"""What a run may remove or replace in its output (:mod:`ti_dk.output.claim`): only what it can tell
it wrote; the user's files anywhere among its paths survive every command, byte for byte."""
import os
import shutil
import signal

import h5py
import numpy as np
import pytest

from ti_dk import ConfigError, load_scene, run

from ..helpers import file_tree, no_hang

STEM = "ellipse2d_fv"


def _scene():
    """10 steps of a 2D scene: run file, frames, snapshots, a 4-frame movie, checkpoints every 3 steps."""
    return load_scene("ellipse2d", method="fv", compare="none", cells=[8, 8], t_end=0.01,
                      output_times=[0.0, 0.001], movie_frames=4)


def _stopped_overwrite(out, monkeypatch):
    """``--overwrite`` of ``out`` stopped by SIGTERM right after its first checkpoint."""
    from ti_dk.control import handlers
    from ti_dk.control.signals import Stopped, stop_on_signals

    write = handlers.Checkpoints.write

    def stop_after(self, n):
        write(self, n)
        os.kill(os.getpid(), signal.SIGTERM)

    with monkeypatch.context() as m:
        m.setattr(handlers.Checkpoints, "write", stop_after)
        with stop_on_signals(), pytest.raises(Stopped):
            run(_scene(), out=out, overwrite=True, checkpoint_every=3)


@pytest.fixture(scope="module")
def every_part(tmp_path_factory):
    """An output holding every path a run owns: a finished result with its movie, a checkpoint and
    the stage of a stopped replace."""
    out = tmp_path_factory.mktemp("claim") / "out"
    run(_scene(), out=out, movie=True)
    with pytest.MonkeyPatch.context() as m:
        _stopped_overwrite(out, m)
    names = {p.name for p in out.iterdir()}
    assert names == {f"{STEM}.h5", f"{STEM}_frames", f"{STEM}_openpmd", f"{STEM}.mp4", f"{STEM}_checkpoint.h5",
                     f".{STEM}.partial"}, names
    assert (out / f".{STEM}.partial" / f"{STEM}_frames").is_dir()
    return out


def _plant(out, where):
    """The user's own file at ``where`` (replacing ti_dk's there, if any); its path."""
    path = out / where.format(stem=STEM)
    if path.exists():
        path.unlink()
    if where.endswith("checkpoint.h5"):
        with h5py.File(path, "w") as f:
            f["mine"] = np.arange(3)
            f.attrs["scene"] = "mine"  # a name ti_dk uses too, but not a checkpoint
    else:
        path.write_bytes(b"the user's own bytes")
    return path


COMMANDS = {"run": {}, "overwrite": {"overwrite": True}, "restart": {"restart": True},
            "stopped": {"stopped": True}}


@pytest.mark.parametrize("where", ["{stem}_frames/mine.txt", "{stem}_openpmd/mine.txt", "{stem}.mp4",
                                   ".{stem}.partial/notes.txt", ".{stem}.partial/{stem}_frames/mine.txt",
                                   "{stem}.lock", "{stem}_checkpoint.h5"])
@pytest.mark.parametrize("command", COMMANDS)
def test_a_foreign_file_among_the_outputs_survives_every_command(every_part, tmp_path, monkeypatch, where, command):
    out = tmp_path / "out"
    shutil.copytree(every_part, out)
    mine = _plant(out, where)
    before = file_tree(out)
    kw = COMMANDS[command]
    with pytest.raises(ConfigError) as err:
        if "stopped" in kw:
            _stopped_overwrite(out, monkeypatch)
        else:
            restart = out / f"{STEM}_checkpoint.h5" if "restart" in kw else None
            run(_scene(), out=out, overwrite=kw.get("overwrite", False) or restart is not None, restart=restart)
    assert str(mine) in str(err.value) and "\n" not in str(err.value)
    assert file_tree(out) == before


def test_what_ti_dk_wrote_is_still_replaced_and_removed(every_part, tmp_path):
    """The same output without a foreign file: a restart finishes the stopped replace, and a run
    without --movie then removes the movie its run file records; nothing is left beside the result."""
    out = tmp_path / "out"
    shutil.copytree(every_part, out)
    (out / f"{STEM}.lock").write_text("4242\n")  # a stale lock of ti_dk's
    run(_scene(), out=out, overwrite=True, restart=out / f"{STEM}_checkpoint.h5", movie=True)
    with h5py.File(out / f"{STEM}.h5", "r") as f:
        assert f.attrs["complete"] and f.attrs["movie_bytes"] == (out / f"{STEM}.mp4").stat().st_size
    run(_scene(), out=out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == sorted([f"{STEM}.h5", f"{STEM}_frames", f"{STEM}_openpmd",
                                                           f"{STEM}_checkpoint.h5"])


@pytest.mark.parametrize("where", ["{stem}.h5", "{stem}.lock", "{stem}_checkpoint.h5", "{stem}.mp4"])
def test_a_fifo_at_an_output_path_is_refused_at_once(tmp_path, where):
    out = tmp_path / "out"
    out.mkdir()
    fifo = out / where.format(stem=STEM)
    os.mkfifo(fifo)
    with no_hang(), pytest.raises(ConfigError, match="is not a regular file") as err:
        run(_scene(), out=out)
    assert str(fifo) in str(err.value) and [p.name for p in out.iterdir()] == [fifo.name]


@pytest.mark.parametrize("fails", [False, True])
def test_a_file_put_in_the_stage_during_a_replace_stays(every_part, tmp_path, monkeypatch, fails):
    """The user's file appears in the stage while a replace runs; the replace finishes (the stage
    then holds only that file) or fails (the stage, with that file, stays)."""
    from ti_dk.control.controller import Controller
    from ti_dk.output.files import OutputError

    out = tmp_path / "out"
    shutil.copytree(every_part, out)
    shutil.rmtree(out / f".{STEM}.partial")
    (out / f"{STEM}_checkpoint.h5").unlink()  # a failed replace keeps no stage then
    record = Controller.record

    def meanwhile(self, n):
        record(self, n)
        if n == 1:
            (out / f".{STEM}.partial" / "notes.txt").write_text("mine")
            if fails:
                raise OSError(28, "No space left on device", "injected")

    monkeypatch.setattr(Controller, "record", meanwhile)
    if fails:
        with pytest.raises(OutputError):
            run(_scene(), out=out, overwrite=True)
    else:
        run(_scene(), out=out, overwrite=True)
    assert (out / f".{STEM}.partial" / "notes.txt").read_text() == "mine"
    assert len(list((out / f".{STEM}.partial").iterdir())) == (4 if fails else 1)
