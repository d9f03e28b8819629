"""Bias and standard errors of per-cell moments against exact answers: ensembles drawn from known
distributions, each cell an independent replicate, so the spread over cells is the true sampling error."""
import numpy as np
import pytest

from ti_dk.core import bias
from ti_dk.core.stats import Moments


def _exact_poisson(lam):
    return {"mean": lam, "variance": lam, "skewness": lam**-0.5, "kurtosis": 3 + 1 / lam}


def test_moments_are_those_of_the_streaming_statistics():
    x = np.random.default_rng(0).poisson(3.0, size=(1, 50, 7)).astype(float)
    value, _ = bias.moments(x)
    m = Moments((7,))
    m.add(x[0])
    for k in bias.MOMENTS:
        np.testing.assert_allclose(value[k], getattr(m, k), rtol=1e-12)


@pytest.mark.parametrize("draw", ["poisson", "gamma"])
def test_standard_errors_match_the_spread_of_the_estimates(draw):
    """SE from each ensemble's own samples (delta method, moments up to the 8th) against the spread of
    the estimates over 4000 independent ensembles of 400 members."""
    rng = np.random.default_rng(1)
    cells, members = 1000, 1500
    x = rng.poisson(4.0, (1, members, cells)) if draw == "poisson" else rng.gamma(4.0, size=(1, members, cells))
    value, se = bias.moments(x.astype(float))
    for k in bias.MOMENTS:
        ratio = value[k].std() / np.sqrt(np.mean(se[k] ** 2))
        assert 0.92 < ratio < 1.08, (k, ratio)


def test_standard_errors_count_a_member_once_when_its_samples_are_correlated():
    """Five samples a member, each its member's value plus small noise: the SE is that of the
    members (M samples), not of 5 M independent ones (which would be √5 too small)."""
    rng = np.random.default_rng(2)
    cells, members = 1000, 600
    base = rng.poisson(6.0, (1, members, cells)).astype(float)
    x = base + 0.1 * rng.standard_normal((5, members, cells))
    value, se = bias.moments(x)
    for k in bias.MOMENTS:
        ratio = value[k].std() / np.sqrt(np.mean(se[k] ** 2))
        assert 0.9 < ratio < 1.1, (k, ratio)


def test_bias_of_a_known_pair_and_its_z_scores():
    """Poisson(5.5) against Poisson(5): each cell's bias is the exact difference within its SE (z
    over cells has mean 0 and spread 1), and the noise-free RMS bias is the exact one."""
    rng = np.random.default_rng(3)
    cells, members, planned = 1000, 1500, 200_000
    cand = bias.Ensemble([rng.poisson(5.5, (1, members, cells)).astype(float)])
    ref = bias.Ensemble([rng.poisson(5.0, (1, members, cells)).astype(float)])
    a, r = _exact_poisson(5.5), _exact_poisson(5.0)
    for k in bias.MOMENTS:
        b = cand.whole[0][k][0] - ref.whole[0][k][0]
        z = (b - (a[k] - r[k])) / np.hypot(cand.whole[1][k][0], ref.whole[1][k][0])
        assert abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1, (k, z.mean(), z.std())
    out = bias.compare(cand, ref, planned, np.ones((1, cells), bool))
    for k in bias.MOMENTS:
        exact = abs(a[k] - r[k])
        square, se = out[k, "bias"]
        assert abs(square - exact**2) < 3 * se, (k, square, exact**2, se)
    # in SEs at the planned ensemble: the exact bias over the exact SE of N members of Poisson(5)
    for k, sd1 in (("mean", 5**0.5), ("variance", (25 * (r["kurtosis"] - 1)) ** 0.5)):
        square, se = out[k, "z"]
        assert abs(square - (abs(a[k] - r[k]) / (sd1 / planned**0.5)) ** 2) < 3 * se, k
    assert bias.root(*out["mean", "rel"])[0] == pytest.approx(0.5 / 5.0, rel=0.05)


@pytest.mark.parametrize("lam", [3.0, 3.3])
def test_summaries_scatter_as_their_stated_standard_errors(lam):
    """Over 20 independent pilots (Poisson(lam) against Poisson(3), two rows of 60 cells, 200
    members): the summary's square averages the exact one (0 without bias) and scatters as its SE."""
    rng = np.random.default_rng(4)
    squares, ses = [], []
    for _ in range(20):
        cand = bias.Ensemble([rng.poisson(lam, (1, 200, 60)).astype(float) for _ in range(2)])
        ref = bias.Ensemble([rng.poisson(3.0, (1, 200, 60)).astype(float) for _ in range(2)])
        out = bias.compare(cand, ref, 20_000, np.ones((2, 60), bool))
        squares.append([out[k, "bias"][0] for k in bias.MOMENTS])
        ses.append([out[k, "bias"][1] for k in bias.MOMENTS])
    squares, ses = np.array(squares), np.array(ses)
    exact = np.array([(_exact_poisson(lam)[k] - _exact_poisson(3.0)[k]) ** 2 for k in bias.MOMENTS])
    assert np.all(np.abs(squares.mean(axis=0) - exact) < 3 * squares.std(axis=0) / np.sqrt(20)), squares.mean(0)
    ratio = squares.std(axis=0) / np.sqrt(np.mean(ses**2, axis=0))
    assert np.all((0.65 < ratio) & (ratio < 1.5)), ratio


def test_differ_and_root():
    assert bias.root(4.0, 5.0) == (2.0, 0.0, 3.0)
    assert not bias.differ((1.0, 1.0), (3.0, 1.0)) and bias.differ((1.0, 0.5), (3.0, 0.5))
    ref = bias.Ensemble([np.ones((1, 4, 2))])
    assert bias.compare(ref, ref, 10, np.ones((1, 2), bool))["kurtosis", "z"] == (0.0, 0.0)
