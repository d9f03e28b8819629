"""Checkpoints: an untouched one is accepted; every damaged or edited one is refused with one line."""
import re
import shutil

import h5py
import numpy as np
import pytest

import ti_dk
from ti_dk import load_scene, run
from ti_dk.control.checkpoint import read_checkpoint
from ti_dk.methods.registry import make_solver


# -- damaged checkpoints: every edit is refused with one line before anything is loaded ---------
@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    d = tmp_path_factory.mktemp("ckpt")
    out = {}
    for method in ("hybrid", "particle"):
        scene = load_scene("ellipse2d", method=method, cells=[16, 16], t_end=0.004, compare="none", regrid_interval=4,
                           output_times=[0.0, 0.002])
        run(scene, out=d, snapshots=False, frames=False, checkpoint_every=5)
        out[method] = scene, d / f"ellipse2d_{method}_checkpoint.h5", make_solver(scene, scene.initial_ppc)
    return out


def _set(name, value):
    def edit(f):
        f[name][...] = value
    return edit


def _item(name, index, value):
    def edit(f):
        a = f[name][()]
        a[index] = value(a[index]) if callable(value) else value
        f[name][...] = a
    return edit


def _attr(name, value):
    def edit(f):
        f.attrs[name] = value(f.attrs[name]) if callable(value) else value
    return edit


def _delete(name):
    def edit(f):
        del f[name]
    return edit


def _region(f):  # cover one more cell that holds no particle
    cov = f["solver/covered"][()]
    free = np.argwhere(cov[0] == 0)[0]
    cov[(0, *free)] = 1
    f["solver/covered"][...] = cov


EDITS = [  # (method, edit, what the message says)
    ("hybrid", _item("solver/x", (0, 0, 0), np.nan), "NaN"),
    ("hybrid", _item("solver/x", (0, 0, 1), 5.0), "outside the domain"),
    ("hybrid", _item("solver/x", (0, 0, 0), -0.25), "outside the domain"),
    ("hybrid", _item("solver/n_real", 0, lambda n: n - 1), "differ from its particle counts"),
    ("hybrid", _item("solver/n_real", 0, lambda n: 10**6), "do not fit"),
    ("hybrid", _item("solver/spde_q", (0, 8, 8), -1e6), "differ from its particle counts|diagnostics say"),
    ("hybrid", _item("solver/spde_q", (0, 0, 0), -1e6), "differ from its particle counts|diagnostics say"),
    ("hybrid", _item("solver/spde_q", (0, 8, 8), np.nan), "NaN"),
    ("hybrid", _region, "region"),
    ("hybrid", _attr("step", lambda s: s - 1), "diagnostics do not end"),
    ("hybrid", _attr("step", lambda s: s + 1), "is outside"),
    ("hybrid", _attr("step", 0), "step 0 is outside"),
    ("hybrid", _attr("step", 10**6), "is outside"),
    ("hybrid", _delete("solver/spde_q"), "state has keys"),
    ("hybrid", _delete("diag/mass"), "diagnostics lack mass"),
    ("hybrid", _delete("times"), "times"),
    ("hybrid", _delete("rows/0"), "doesn't exist"),
    ("hybrid", _delete("rows"), "statistics rows"),
    ("hybrid", _attr("scene", lambda s: s.replace('"seed": 1', '"seed": 2')), "other scene settings"),
    ("particle", _item("solver/x", (0, 3, 0), np.inf), "NaN"),
    ("particle", _item("solver/x", (0, 3, 1), 1.0), "outside the domain"),
    ("particle", _item("solver/n_alive", 0, lambda n: n - 5), "particles where the diagnostics say"),
    ("particle", _delete("solver/n_alive"), "state has keys"),
]


@pytest.mark.parametrize("method, edit, message", EDITS)
def test_every_edited_checkpoint_is_refused(checkpoints, tmp_path, method, edit, message):
    scene, ckpt, solver = checkpoints[method]
    bad = tmp_path / "edited.h5"
    shutil.copy(ckpt, bad)
    with h5py.File(bad, "r+") as f:
        edit(f)
    with pytest.raises(ti_dk.ConfigError) as err:
        read_checkpoint(bad, scene, solver, None)
    assert re.search(message, str(err.value)) and "\n" not in str(err.value) and "unstable" not in str(err.value)


@pytest.mark.parametrize("method", ["hybrid", "particle"])
def test_an_untouched_checkpoint_is_accepted_and_broken_files_refused(checkpoints, tmp_path, method):
    scene, ckpt, solver = checkpoints[method]
    assert read_checkpoint(ckpt, scene, solver, None).step == 15
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    with pytest.raises(ti_dk.ConfigError, match="not a readable checkpoint|damaged checkpoint"):
        read_checkpoint(truncated, scene, solver, None)
