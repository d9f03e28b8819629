"""Exact answers the solvers are checked against (and that the figures draw).

Counts are in particles per cell. Skewness is κ3/κ2^{3/2}; kurtosis is non-excess, κ4/κ2² + 3.
"""
from __future__ import annotations

import math

import numpy as np


def _from_cumulants(k1, k2, k3, k4):
    k2 = np.asarray(k2, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return {"mean": np.asarray(k1, dtype=np.float64), "variance": k2,
                "skewness": k3 / k2**1.5, "kurtosis": k4 / k2**2 + 3.0}


def binomial_moments(n: int, p: float) -> dict[str, float]:
    """Moments of Binomial(n, p): the count in one of M cells holding N uniform particles (p = 1/M)."""
    q = 1.0 - p
    return _from_cumulants(n * p, n * p * q, n * p * q * (1 - 2 * p), n * p * q * (1 - 6 * p * q))


def poisson_binomial_moments(p: np.ndarray, axis: int = 0) -> dict[str, np.ndarray]:
    """Moments of a sum of independent Bernoulli(p_j) along ``axis`` (cumulants add)."""
    q = 1.0 - p
    return _from_cumulants(p.sum(axis), (p * q).sum(axis), (p * q * (1 - 2 * p)).sum(axis),
                           (p * q * (1 - 6 * p * q)).sum(axis))


def _box_gauss_antiderivative(x, s):
    """G with G'' = Gaussian density of std s: G(x) = x Φ(x/s) + s φ(x/s)."""
    z = x / s
    phi = np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    Phi = 0.5 * np.vectorize(math.erfc)(-z / math.sqrt(2))
    return x * Phi + s * phi


def poisson_binomial_pmf(p: np.ndarray, repeats: np.ndarray | None = None) -> np.ndarray:
    """Exact PMF of a sum of independent Bernoulli(p_j) (each repeated ``repeats[j]`` times), by
    convolving the binomial PMFs of the groups."""
    repeats = np.ones(len(p), dtype=int) if repeats is None else np.asarray(repeats, dtype=int)
    pmf = np.ones(1)
    for pj, r in zip(p, repeats):
        if r == 0:
            continue
        k = np.arange(r + 1)
        binom = np.array([math.comb(r, int(i)) for i in k], dtype=np.float64) * pj**k * (1 - pj) ** (r - k)
        pmf = np.convolve(pmf, binom)
    return pmf


def cell_transition(cells: int, length: float, t: float, images: int = 3) -> np.ndarray:
    """P[j, i]: probability that a Brownian particle (D = ½, variance t) started uniformly in cell j
    of a periodic 1D domain ends in cell i. Exact: (G(d+h) − 2G(d) + G(d−h))/h, summed over images."""
    h = length / cells
    d = (np.arange(cells)[None, :] - np.arange(cells)[:, None]) * h
    s = math.sqrt(t)
    P = np.zeros((cells, cells))
    for m in range(-images, images + 1):
        dm = d + m * length
        P += (_box_gauss_antiderivative(dm + h, s) - 2 * _box_gauss_antiderivative(dm, s)
              + _box_gauss_antiderivative(dm - h, s)) / h
    return P


def particle_counts_periodic1d(ppc0: np.ndarray, length: float, t: float) -> dict[str, np.ndarray]:
    """Exact count moments per cell at time t for ``ppc0[j]`` (integers) particles started uniformly
    in each cell j of a periodic 1D domain: a Poisson-binomial sum over all particles."""
    counts = np.asarray(ppc0)
    if not np.allclose(counts, np.round(counts)):
        raise ValueError("the exact answer needs whole particle numbers per cell")
    P = cell_transition(len(counts), length, t)
    p = np.repeat(P, np.round(counts).astype(int), axis=0)  # one row per particle
    return poisson_binomial_moments(p, axis=0)


def linear_scheme_variance(cells: tuple[int, ...], dt_over_dx2: tuple[float, ...], ppc: float,
                           steps: int | None = None) -> float:
    r"""Exact per-cell count variance of the linearised (Gaussian) scheme around a uniform density.

    Mode k of the discrete Fourier transform has amplification g_k = 1 − 2 S_k and, in count units,
    noise variance 4 λ S_k per step, with S_k = Σ_a (Δt/Δx_a²) sin²(π k_a / M_a). Its stationary
    variance is λ / (1 − S_k); started from the uniform state it is λ (1 − g_k^{2n}) / (1 − S_k)
    after n steps. The cell variance is the mean over all modes, the k = 0 mode (total mass) being
    exactly zero: λ (1 − 1/M) · mean_{k≠0} 1/(1 − S_k) in the stationary case.
    """
    grids = np.meshgrid(*[np.arange(m) for m in cells], indexing="ij")
    S = sum(c * np.sin(np.pi * k / m) ** 2 for c, k, m in zip(dt_over_dx2, grids, cells))
    var = ppc / (1.0 - S)
    if steps is not None:
        var = var * (1.0 - (1.0 - 2.0 * S) ** (2 * steps))
    var.flat[0] = 0.0
    return float(var.mean())


def sampling_se(pmf: np.ndarray, members: int, replicas: int = 400, seed: int = 0) -> dict[str, float]:
    """Standard errors of the sample mean, variance, skewness and kurtosis of ``members`` draws from
    an exact PMF on 0, 1, 2, …, found by drawing ``replicas`` independent ensembles from it."""
    rng = np.random.default_rng(seed)
    x = rng.choice(len(pmf), size=(replicas, members), p=pmf / pmf.sum()).astype(float)
    m = x.mean(axis=1, keepdims=True)
    d = x - m
    m2 = (d**2).mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        skew = (d**3).mean(axis=1) / m2**1.5
        kurt = (d**4).mean(axis=1) / m2**2
    return {"mean": x.mean(axis=1).std(), "variance": x.var(axis=1, ddof=1).std(),
            "skewness": np.nanstd(skew), "kurtosis": np.nanstd(kurt)}


def void_reference(ppc0: np.ndarray, length: float, t: float, members: int, cells: np.ndarray,
                   replicas: int = 200) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The exact per-cell moments of particle counts at time ``t`` from the integer initial counts
    ``ppc0`` (periodic 1D), and the sampling standard errors of an ensemble of ``members`` in the
    ``cells`` asked for (NaN elsewhere)."""
    exact = particle_counts_periodic1d(ppc0, length, t)
    P = cell_transition(len(ppc0), length, t)
    se = {k: np.full(len(ppc0), np.nan) for k in exact}
    for i in np.flatnonzero(cells):
        for k, v in sampling_se(poisson_binomial_pmf(P[:, i], ppc0), members, replicas, seed=int(i)).items():
            se[k][i] = v
    return exact, se
