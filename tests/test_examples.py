"""The scripts in examples/ run as a user runs them (``python examples/X.py --small``, from a
folder outside the checkout) and print what they promise."""
import os
import re
import subprocess
import sys

import pytest

from .helpers import ROOT

EXAMPLES = sorted(p.name for p in (ROOT / "examples").glob("*.py"))


def _run(name, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")
    done = subprocess.run([sys.executable, str(ROOT / "examples" / name), "--small"], cwd=tmp_path, env=env,
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
    assert len(re.findall(r"^\s+2\d\s", out, re.M)) + len(re.findall(r"^\s+30\s", out, re.M)) == 11


def test_own_scene_loads_the_written_toml_and_runs_the_hybrid(tmp_path):
    out = _run("own_scene.py", tmp_path)
    assert out.startswith("lowdisk2d: A low-density disk in a bulk, fed by a reservoir on the left wall; (16, 16) cells")
    # the disk (2 per cell) is below threshold 6: the region is not empty
    covered = int(re.search(r"particle region: (\d+) cells", out).group(1))
    assert 0 < covered < 256
    assert "lowdisk2d_hybrid.h5" in out


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
