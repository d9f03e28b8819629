"""``python -m ti_dk.scene`` as a user runs it: results, one-line errors, thread-count independence."""
import json
import os
import signal
import subprocess
import sys
import time

import h5py
import imageio.v3 as iio
import numpy as np
import pytest


def cli(*args, cwd):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run([sys.executable, "-m", "ti_dk.scene", *args, "--no-progress"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def _stats(path):
    with h5py.File(path) as f:
        assert f.attrs["complete"]
        return {k: f[f"stats/{k}"][:] for k in ("mean", "variance", "skewness", "kurtosis")}


@pytest.mark.parametrize("method", ["fv", "particle", "hybrid"])
def test_same_seed_same_bits_on_one_and_two_threads(tmp_path, method):
    common = ["void1d", "--method", method, "--ensemble", "64", "--t-end", "0.0005", "--set", "cells=[40]"]
    out = {}
    for threads, seed in ((1, 5), (2, 5), (2, 6)):
        d = tmp_path / f"t{threads}s{seed}"
        r = cli(*common, "--threads", str(threads), "--seed", str(seed), "--out", str(d), cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        out[threads, seed] = _stats(d / f"void1d_{method}.h5")
    for k in out[1, 5]:
        assert np.array_equal(out[1, 5][k], out[2, 5][k], equal_nan=True), k
    assert not np.array_equal(out[2, 5]["mean"], out[2, 6]["mean"])


@pytest.mark.parametrize(
    "args, message",
    [
        (["nosuchscene"], "unknown scene 'nosuchscene'"),
        (["void1d", "--set", "cells=[0]"], "cells = 0"),
        (["void1d", "--set", "C=2.0"], "beyond the explicit stability limit"),
        (["void1d", "--set", "colour=red"], "unknown key 'colour'"),
        (["void1d", "--set", "C"], "write KEY=VALUE"),
        (["void1d", "--arch", "metal"], "backend 'metal' is not supported"),
        (["void1d", "--arch", "cuda"], "'cuda' backend is not available"),
    ],
)
def test_bad_input_exits_2_with_one_line_and_no_file(tmp_path, args, message):
    if "cuda" in args:
        pytest.importorskip("taichi")
        import taichi as ti

        if ti.lang.impl.current_cfg().arch == ti.cuda:  # pragma: no cover - only where a GPU exists
            pytest.skip("a CUDA device is present")
    r = cli(*args, "--out", str(tmp_path / "out"), cwd=tmp_path)
    lines = [ln for ln in r.stderr.splitlines() if not ln.startswith("[Taichi]")]
    assert r.returncode == 2
    assert lines == [lines[0]] and lines[0].startswith("ti_dk: error: ") and message in lines[0], r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("scene, args, frames", [
    ("ellipse2d", ["--quick"], 4),
    ("sphere3d", ["--set", "cells=[16,16,16]", "--set", "regrid_interval=2", "--t-end", "0.0015"], 3),
])
def test_scene_smoke_frames_snapshots_and_negative_counts(tmp_path, scene, args, frames):
    r = cli(scene, *args, "--out", str(tmp_path), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    pngs = sorted((tmp_path / f"{scene}_hybrid_frames").glob("frame_*.png"))
    assert len(pngs) == frames
    img = iio.imread(pngs[-1])
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 400
    assert len(list((tmp_path / f"{scene}_hybrid_openpmd").glob("data*.h5"))) == frames
    with h5py.File(tmp_path / f"{scene}_hybrid.h5") as f:
        assert f.attrs["complete"]
        neg, neg_fv = f["frames/negative_cells"][:], f["frames/compare_negative_cells"][:]
        assert len(neg) == frames and f["regrid/step"].shape[0] > 1
        timing = json.loads(f.attrs["timing"])
        assert {"spde", "particles", "regrid", "render", "io", "compare"} <= set(timing)
    # the hybrid keeps every frame free of negative densities; fv on the same start does not
    assert not neg.any() and neg_fv.max() > 0


def test_sigterm_leaves_a_valid_checkpoint_and_a_readable_file(tmp_path):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    args = [sys.executable, "-m", "ti_dk.scene", "ellipse2d", "--set", "cells=[96,96]", "--checkpoint-every", "5",
            "--no-progress", "--no-frames", "--out", str(tmp_path)]
    p = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ckpt = tmp_path / "ellipse2d_hybrid_checkpoint.h5"
    deadline = time.time() + 300
    while not ckpt.exists() and time.time() < deadline and p.poll() is None:
        time.sleep(0.2)
    time.sleep(1.0)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143, err
    assert [ln for ln in err.splitlines() if not ln.startswith("[Taichi]")][-1].startswith("ti_dk: error: stopped")
    with h5py.File(ckpt) as f:
        step = int(f.attrs["step"])
        assert step % 5 == 0 and f["solver/spde_q"].shape == (1, 96, 96)
    with h5py.File(tmp_path / "ellipse2d_hybrid.h5") as f:
        assert not f.attrs["complete"] and "SIGTERM" in f.attrs["error"]
        assert f["stats/mean"].shape[0] >= 1
    assert not list(tmp_path.glob("*.tmp"))
    r = cli("ellipse2d", "--set", "cells=[96,96]", "--no-frames", "--restart", str(ckpt), "--out", str(tmp_path),
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "ellipse2d_hybrid.h5") as f:
        assert f.attrs["complete"] and f["stats/mean"].shape[0] == 4
