"""The figure commands on small ensembles: files written, and the paper's findings in the data."""
import h5py
import matplotlib
import numpy as np
import pytest

from studies import figures
from ti_dk.core import theory

from ..helpers import command

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


@pytest.mark.slow  # statistical: 6 equilibrium runs (~15 s)
def test_fig2_pdfs(tmp_path):
    data = figures.fig2(10, tmp_path, plt)
    assert (tmp_path / "fig2.png").stat().st_size > 10_000
    with h5py.File(tmp_path / "fig2.h5") as f:
        assert set(f) == {"ppc5", "ppc1"}
    for ppc in (5, 1):
        k, pdf = data[f"ppc{ppc}/particle"]
        k = k.astype(int)
        assert np.isclose(pdf.sum(), 1) and pdf[k < 0].sum() == 0  # particles are never negative
        exact = theory.poisson_binomial_pmf(np.array([0.01]), np.array([100 * ppc]))
        inside = (k >= 0) & (k < exact.size)
        assert np.abs(pdf[inside] - exact[k[inside]]).max() < 0.02
        assert data[f"ppc{ppc}/gaussian"][1][k < 0].sum() > 0.003  # the Gaussian SPDE goes negative


@pytest.mark.slow  # statistical: 9 equilibrium runs (~25 s)
def test_fig3_reproduces_the_papers_findings(tmp_path):
    data = figures.fig3(20, tmp_path, plt, ppcs=(1, 5, 50))
    exact = {p: theory.binomial_moments(100 * p, 0.01) for p in (1, 5, 50)}
    part, fv, gau = data["particle"], data["fv"], data["gaussian"]
    # columns: ppc, skewness, its error, kurtosis, its error
    for row in part:  # the particle curve lies on the exact binomial within its error bars
        p = int(row[0])
        assert abs(row[1] - exact[p]["skewness"]) < 4 * row[2] + 0.01
        assert abs(row[3] - exact[p]["kurtosis"]) < 4 * row[4] + 0.01
    assert np.all(np.abs(gau[:, 1]) < 0.02) and np.all(np.abs(gau[:, 3] - 3) < 0.03)  # stays Gaussian
    assert abs(part[2, 1]) < 0.2 and abs(part[2, 3] - 3) < 0.1  # near Gaussian at 50 per cell
    assert part[0, 1] > 0.8 and fv[0, 1] > 0.8  # clearly skewed at 1 per cell, particle and fv alike
    assert fv[0, 3] - exact[1]["kurtosis"] > 4 * fv[0, 4]  # fv's kurtosis departs from the exact at 1 per cell


def test_fig4_command_takes_its_sizes_from_the_scene(tmp_path):
    r = command("studies.figures", "fig4", "--ensemble", "4", "--set", "cells=[20]", "--set", "t_end=0.001",
              "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "fig4.png").stat().st_size > 10_000
    for m in ("particle", "fv", "gaussian", "hybrid"):
        with h5py.File(tmp_path / "runs" / "fig4" / f"void1d_{m}.h5") as f:
            assert f.attrs["complete"] and f["stats/mean"].shape[1:] == (20,)
    with h5py.File(tmp_path / "fig4.h5") as f:
        exact = f["exact"][:]
    # the exact answer on the scene's 20 cells and its last output time, not on 100 cells
    dt = 0.0625 / 20**2
    t = round(0.001 / dt) * dt
    want = theory.particle_counts_periodic(np.where(np.abs((np.arange(20) + 0.5) / 20 - 0.5) <= 0.25, 0, 20), 1.0, dt,
                                           round(t / dt))
    assert exact.shape == (4, 20) and np.allclose(exact[0], want["mean"]) and np.allclose(exact[1], want["variance"])


def test_figure_command_bad_input_exits_2_with_one_line(tmp_path):
    r = command("studies.figures", "fig2", "--set", "colour=red", "--out", str(tmp_path))
    lines = [ln for ln in r.stderr.splitlines() if not ln.startswith("[Taichi]")]
    assert r.returncode == 2 and len(lines) == 1 and "unknown key 'colour'" in lines[0], r.stderr
    assert not (tmp_path / "fig2.png").exists()
