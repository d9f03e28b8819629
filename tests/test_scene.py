"""``python -m ti_dk.scene`` as a user runs it: results, one-line errors, thread-count independence."""
import os
import subprocess
import sys

import h5py
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
