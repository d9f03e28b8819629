"""Checkpoints: an untouched one is accepted; every damaged or edited one is refused with one line."""
import re
import shutil

import h5py
import numpy as np
import pytest

import ti_dk
from ti_dk import load_scene, run
from ti_dk.control.checkpoint import content_digest, read_checkpoint
from ti_dk.control.registry import make_solver


# -- damaged checkpoints: every edit is refused with one line before anything is loaded ---------
@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    d = tmp_path_factory.mktemp("ckpt")
    out = {}
    for method in ("hybrid", "particle"):
        scene = load_scene("ellipse2d", method=method, cells=[16, 16], t_end=0.004, compare="none", regrid_interval=4,
                           output_times=[0.0, 0.002], ensemble=2 if method == "particle" else 1)
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
    ("hybrid", _attr("scene", lambda s: s.replace('"seed": 1', '"seed": 2')), r"other settings \(.*seed: checkpoint 2, now 1"),
    ("particle", _item("solver/x", (0, 3, 0), np.inf), "NaN"),
    ("particle", _item("solver/x", (0, 3, 1), 1.0), "outside the domain"),
    ("particle", _item("solver/n_alive", 0, lambda n: n - 5), "particles where the diagnostics say"),
    ("particle", _delete("solver/n_alive"), "state has keys"),
]


def _swap(name, a, b):  # exchange two entries (members, cells): every sum, the mass included, unchanged
    def edit(f):
        v = f[name][()]
        v[a], v[b] = v[b].copy(), v[a].copy()
        f[name][...] = v
    return edit


def _edited(ckpt, tmp_path, edit, digest: bool):
    """A copy of ``ckpt`` with ``edit`` made, its digest recomputed if ``digest`` (as a forger would)."""
    bad = tmp_path / "edited.h5"
    shutil.copy(ckpt, bad)
    with h5py.File(bad, "r+") as f:
        edit(f)
        if digest:
            f.attrs["digest"] = content_digest(f)
    return bad


def _refused(path, scene, solver, message):
    with pytest.raises(ti_dk.ConfigError) as err:
        read_checkpoint(path, scene, solver, None)
    assert re.search(message, str(err.value)) and "\n" not in str(err.value) and "unstable" not in str(err.value), \
        str(err.value)


@pytest.mark.parametrize("method, edit, message", EDITS)
def test_every_edited_checkpoint_is_refused(checkpoints, tmp_path, method, edit, message):
    """By its content checks even when the digest was recomputed to match, and by the digest when not."""
    scene, ckpt, solver = checkpoints[method]
    _refused(_edited(ckpt, tmp_path, edit, digest=True), scene, solver, message)
    other = "other settings" in message
    _refused(_edited(ckpt, tmp_path, edit, digest=False), scene, solver, message if other else "differs from its digest")


@pytest.mark.parametrize("method, edit", [
    ("particle", _swap("solver/x", (0,), (1,))),  # the two members exchanged
    ("particle", _swap("solver/x", (0, 0), (0, 1))),  # two particles of member 0 exchanged
    ("hybrid", _swap("solver/spde_q", (0, 0, 0), (0, 15, 15))),  # two cells exchanged
    ("hybrid", _attr("timing", lambda t: t.replace("{", '{"x": 1, ', 1))),
])
def test_a_swap_that_keeps_every_sum_is_refused_by_the_digest(checkpoints, tmp_path, method, edit):
    scene, ckpt, solver = checkpoints[method]
    bad = _edited(ckpt, tmp_path, edit, digest=False)
    with h5py.File(bad) as f, h5py.File(ckpt) as g:  # the edit changed something, not the mass
        assert content_digest(f) != content_digest(g)
    _refused(bad, scene, solver, "differs from its digest")


@pytest.mark.parametrize("edit, message", [
    (_attr("format", 3), r"written by ti_dk .* \(checkpoint format 3\), newer than this"),
    (_attr("ti_dk", "999.0.0"), r"written by ti_dk 999.0.0 .* newer than this"),
    (_attr("format", 1), "old checkpoint without a content digest"),
    (lambda f: f.attrs.__delitem__("digest"), "without a content digest"),
    (_attr("scene", "{[}"), r"damaged checkpoint \(JSONDecodeError\)"),
    (_attr("scene", "[" * 5000 + "]" * 5000), r"damaged checkpoint \(RecursionError\)|other settings"),
])
def test_newer_unversioned_or_unreadable_checkpoints_are_refused(checkpoints, tmp_path, edit, message):
    scene, ckpt, solver = checkpoints["hybrid"]
    _refused(_edited(ckpt, tmp_path, edit, digest=False), scene, solver, message)


def test_a_restart_with_other_settings_names_each_key_and_both_values(checkpoints):
    scene, ckpt, solver = checkpoints["hybrid"]
    other = load_scene("ellipse2d", cells=[16, 16], t_end=0.004, compare="none", regrid_interval=5,
                       output_times=[0.0, 0.002], seed=9)
    with pytest.raises(ti_dk.ConfigError) as err:
        read_checkpoint(ckpt, other, solver, None)
    msg = str(err.value)
    assert "hybrid.regrid_interval: checkpoint 4, now 5" in msg and "method.seed: checkpoint" in msg and ", now 9" in msg
    assert "\n" not in msg


@pytest.mark.parametrize("method", ["hybrid", "particle"])
def test_an_untouched_checkpoint_is_accepted_and_broken_files_refused(checkpoints, tmp_path, method):
    scene, ckpt, solver = checkpoints[method]
    assert read_checkpoint(ckpt, scene, solver, None).step == 15
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    with pytest.raises(ti_dk.ConfigError, match="not a readable checkpoint|damaged checkpoint"):
        read_checkpoint(truncated, scene, solver, None)
