"""The scripts in examples/ run as a user runs them (``python examples/X.py --small``, from a
folder outside the checkout) and print what they promise."""
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .helpers import ROOT

EXAMPLES = sorted(p.name for p in (ROOT / "examples").glob("*.py"))


def _run(name, tmp_path, *args):
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")
    done = subprocess.run([sys.executable, str(ROOT / "examples" / name), "--small", *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_there_are_examples_and_each_has_a_small_size():
    assert {"crossing_rate.py", "ensemble_moments.py", "own_scene.py", "read_output.py"} <= set(EXAMPLES)
    for name in EXAMPLES:
        assert "--small" in (ROOT / "examples" / name).read_text(), name


def test_ensemble_moments_conserves_every_members_particles(tmp_path):
    out = _run("ensemble_moments.py", tmp_path)
    assert "void1d, hybrid, 20 members" in out
    # void1d: 20 per cell in the 50 cells outside the void, periodic: 1000 per member, exactly
    assert "particles per member at the end: 1000.000000 (the start: 1000.000000" in out
    rows = re.findall(r"^\s+(?:2\d|30)\s.*$", out, re.M)
    assert len(rows) == 11
    # each moment with its standard error, the exact value and its z-score: 4 x 4 numbers after the cell
    cols = np.array([row.split()[1:] for row in rows], dtype=float)
    assert cols.shape == (11, 16)
    est, se, exact, z = (cols[:, k::4] for k in range(4))
    assert np.all(se > 0) and np.allclose(z, (est - exact) / se, atol=0.06)
    assert np.abs(z).max() < 4 and f"largest |z| {np.abs(z).max():.1f}" in out  # the hybrid is right


def test_own_scene_loads_the_written_toml_and_runs_the_hybrid(tmp_path):
    out = _run("own_scene.py", tmp_path, "--out", "runs")
    assert out.startswith("lowdisk2d: A low-density disk in a bulk, fed by a reservoir on the left wall; (16, 16) cells")
    # the disk (2 per cell) is below threshold 6: the region is not empty
    covered = int(re.search(r"particle region: (\d+) cells", out).group(1))
    assert 0 < covered < 256
    written = [line.strip() for line in out.split("wrote:\n")[1].splitlines()]
    assert str(tmp_path / "runs" / "lowdisk2d_hybrid.h5") in written or "runs/lowdisk2d_hybrid.h5" in written
    assert all((tmp_path / p).exists() for p in written)  # every path it prints is there after it ends
    out = _run("own_scene.py", tmp_path / "runs")  # without --out: no path printed, nothing written
    assert "wrote:" not in out and "nothing written" in out and sorted(p.name for p in (tmp_path / "runs").iterdir()) \
        == sorted(p.name for p in map(Path, written) if p.parent.name == "runs")  # frames/series.png inside


def test_crossing_rate_gives_the_double_wells_rate_with_its_error_against_the_exact_one(tmp_path):
    out = _run("crossing_rate.py", tmp_path)
    rate, se = map(float, re.search(r"crossing rate left -> right: ([\d.]+) ± ([\d.]+) per", out).groups())
    exact = float(re.search(r"exact \(the 1D walk of the particles\): ([\d.]+);", out).group(1))
    assert exact == pytest.approx(0.1125, abs=5e-4) and 0 < se < 0.08 * exact and abs(rate - exact) < 4 * se


def test_read_output_reads_the_run_file_and_the_openpmd_snapshot(tmp_path):
    out = _run("read_output.py", tmp_path)
    assert "ellipse2d_hybrid.h5: complete = True" in out
    mass = re.search(r"mass ([\d,.]+) -> ([\d,.]+)", out)
    assert mass.group(1) == mass.group(2)  # periodic, hybrid: conserved to round-off
    region = re.findall(r"particle region: (\d+) cells", out)
    assert region and int(region[0]) > 0
    assert re.search(r"^data\d+\.h5: iteration \d+", out, re.M)


@pytest.mark.parametrize("name", EXAMPLES)
def test_every_example_says_what_it_is_and_how_to_run_it(name):
    text = (ROOT / "examples" / name).read_text()
    assert text.startswith('"""') and f"python examples/{name}" in text


@pytest.mark.parametrize("page", ["README.md", "docs/quickstart.md"])
def test_the_python_examples_of_the_readme_and_quickstart_load_without_a_warning(page):
    """Their ``load_scene`` lines run as written with every warning an error (output times past
    t_end were one), and the scene list they print is the shipped one."""
    import warnings

    import ti_dk

    text = (ROOT / page).read_text()
    lines = re.findall(r"^scene = (ti_dk\.load_scene\(.*\))", text, re.M)
    assert lines
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for line in lines:
            eval(line, {"ti_dk": ti_dk})
    for shown in re.findall(r"available_scenes\(\)\)\s+# (\[.*\])", text):
        assert eval(shown) == ti_dk.available_scenes()

