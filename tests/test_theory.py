"""The exact answers themselves, checked by independent routes."""
import math

import numpy as np

from ti_dk import theory


def test_poisson_binomial_cumulants_match_pmf():
    p = np.array([0.05, 0.3, 0.5, 0.9])
    reps = np.array([3, 2, 1, 4])
    pmf = theory.poisson_binomial_pmf(p, reps)
    k = np.arange(len(pmf))
    mean = (k * pmf).sum()
    c = k - mean
    var = (c**2 * pmf).sum()
    m = theory.poisson_binomial_moments(np.repeat(p, reps))
    assert np.isclose(pmf.sum(), 1) and np.isclose(m["mean"], mean) and np.isclose(m["variance"], var)
    assert np.isclose(m["skewness"], (c**3 * pmf).sum() / var**1.5)
    assert np.isclose(m["kurtosis"], (c**4 * pmf).sum() / var**2)


def test_binomial_moments():
    b = theory.binomial_moments(100, 0.01)
    assert np.isclose(b["variance"], 0.99) and np.isclose(b["skewness"], 0.98 / math.sqrt(0.99))


def test_cell_transition_is_stochastic_and_diffusive():
    P = theory.cell_transition(50, 1.0, 0.001)
    assert np.allclose(P.sum(axis=1), 1.0)
    x = (np.arange(50) - 25) * 0.02
    # spread of the end cell: start uniform in the cell (h²/12) plus diffusion t, plus the
    # end-cell discretisation h²/12
    assert np.isclose((P[25] * x**2).sum(), 0.001 + 2 * 0.02**2 / 12, rtol=1e-3)


def test_linear_scheme_variance_limits():
    # C → 0 gives the binomial variance λ(1 − 1/M); many steps reach the stationary value
    assert np.isclose(theory.linear_scheme_variance((100,), (1e-9,), 5.0), 5.0 * 0.99)
    assert np.isclose(theory.linear_scheme_variance((10,), (0.1,), 5.0, steps=100000),
                      theory.linear_scheme_variance((10,), (0.1,), 5.0))
    assert theory.linear_scheme_variance((10,), (0.1,), 5.0, steps=0) == 0.0
