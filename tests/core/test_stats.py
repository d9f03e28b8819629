"""Streaming moments and histograms against direct NumPy computations on the same data."""
import numpy as np

from ti_dk.core.stats import CellStats, Histogram, Moments


def test_pebay_merge_equals_one_pass():
    rng = np.random.default_rng(1)
    x = rng.gamma(0.7, 3.0, size=(1000, 5)) + 1e3  # skewed, with a large offset
    m = Moments((5,))
    for chunk in np.array_split(x, [1, 3, 200, 201, 640]):
        m.add(chunk)
    d = x - x.mean(axis=0)
    assert m.n == 1000
    assert np.allclose(m.mean, x.mean(axis=0), rtol=1e-13)
    assert np.allclose(m.variance, x.var(axis=0, ddof=1), rtol=1e-10)
    assert np.allclose(m.skewness, (d**3).mean(0) / (d**2).mean(0) ** 1.5, rtol=1e-8)
    assert np.allclose(m.kurtosis, (d**4).mean(0) / (d**2).mean(0) ** 2, rtol=1e-8)


def test_histogram_bins_are_one_particle_wide():
    rng = np.random.default_rng(2)
    x = rng.normal(3.0, 2.0, size=(5000, 3))
    h = Histogram((3,), -2, 8)
    h.add(x)
    for c in range(3):
        ref = np.histogram(x[:, c], bins=np.arange(-2.5, 9.0))[0]
        assert np.array_equal(h.counts[c], ref)
        assert h.outside[c] == 5000 - ref.sum()


def test_cell_stats_row_units():
    cs = CellStats((2,), cell_volume=0.5, histogram=(0, 4))
    cs.add(np.array([[2.0, 4.0], [4.0, 8.0]]))  # densities; particles = density * 0.5
    row = cs.row()
    assert np.allclose(row["mean"], [3.0, 6.0])
    assert row["histogram"][0].tolist() == [0, 1, 1, 0, 0] and row["histogram"][1].tolist() == [0, 0, 1, 0, 1]
