"""Helpers shared by several test modules: count moments against exact ones, commands as a user runs them."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

KEYS = ("mean", "variance", "skewness", "kurtosis")
ROOT = Path(__file__).resolve().parent.parent  # the repository root: `python -m studies.*` runs from here


def check_moments(counts_stats, exact, se, cells, z_max=5.0):
    """Every moment within ``z_max`` sampling errors of the exact one in every cell asked for, and no
    bias on average over those cells."""
    for k in KEYS:
        z = (counts_stats[k][cells] - exact[k][cells]) / se[k][cells]
        assert np.all(np.abs(z) < z_max), (k, z.max(), z.min())
        assert abs(z.mean()) < z_max / np.sqrt(z.size) + 0.1, (k, z.mean())


def as_counts(stats, row, vol):
    """One statistics row in particle counts per cell (the units of the exact answers)."""
    return {"mean": stats.mean[row] * vol, "variance": stats.variance[row] * vol**2,
            "skewness": stats.skewness[row], "kurtosis": stats.kurtosis[row]}


def user_env() -> dict:
    """The environment of a command as a user runs it, importing the ti_dk under test (this tree's,
    not whichever one is installed), from any folder."""
    return dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=str(ROOT))


def command(module, *args, cwd=ROOT):
    """``python -m <module> <args>`` as a user runs it (from the repository root by default)."""
    env = user_env()
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)


def digest_on_threads(script: str, threads=(1, 2)) -> list[str]:
    """The last word ``python -c script THREADS`` prints (a state digest), once per thread count:
    Taichi fixes its thread count at ``ti.init``, so each count needs a process of its own."""
    import ti_dk
    env = dict(os.environ, PYTHONPATH=str(Path(ti_dk.__file__).resolve().parent.parent))
    return [subprocess.run([sys.executable, "-c", script, str(t)], env=env, capture_output=True, text=True,
                           check=True).stdout.split()[-1] for t in threads]


def file_tree(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones included) with the SHA-256 of its bytes."""
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}
