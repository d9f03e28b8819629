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
    return fixed_and_poisson_moments(n, 0.0, p)


def fixed_and_poisson_moments(n: float, lam: float, p: float) -> dict[str, float]:
    """Moments of the count in a cell of share ``p`` when ``n`` particles are fixed in number and
    ``Poisson(lam)`` more were drawn: Bin(n, p) + Poisson(lam p), independent (a Poisson count
    thinned by ``p`` stays Poisson), so the cumulants add. The hybrid's total is of this kind:
    the SPDE's content ``n`` is fixed, the particles sampled into the first region Poisson."""
    q = 1.0 - p
    return _from_cumulants(n * p + lam * p, n * p * q + lam * p, n * p * q * (1 - 2 * p) + lam * p,
                           n * p * q * (1 - 6 * p * q) + lam * p)


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


def trap_walk_shares(cells: int, length: float, dt: float, curvature: float, centre: float) -> np.ndarray:
    r"""Each cell's share of the stationary law of the particles' own walk in a harmonic trap
    ``U = ½ k (x − x₀)²``: the exact equilibrium of the time-stepped, clamped Euler–Maruyama walk of
    :class:`ti_dk.methods.particles.Walker`, which is not the Boltzmann ``e^{−U}`` of the SDE.

    The step ``D = clamp(μ + √Δt Z, −Δx, Δx)``, ``μ = −½ k (x − x₀) Δt``, makes ``y = x − x₀`` an
    AR(1) chain ``y ← a y + ε``: ``a = 1 − ½ kΔt (1 − P_c)``, the restoring drift weakened by the
    clamp (``∂E[D]/∂μ = P(|√Δt Z| < Δx) = 1 − P_c``, ``P_c = erfc(c/√2)``, ``c = Δx/√Δt``), and
    ``ε`` the clamped noise, of variance ``v = Δt (1 − P_c − 2cφ(c) + c² P_c)``. Its stationary law
    has variance ``v/(1 − a²)``, wider than the Boltzmann ``1/k`` by about ``kΔt/4``, and is
    Gaussian up to ``ε``'s higher cumulants, which enter damped by ``(1 − a²)^{n/2}/(1 − aⁿ)``.
    Linear in ``μ`` (the clamp's asymmetry is ``O(μ³)``) and with the walls left out (the
    shares are normalised on the domain): tests/core/test_theory.py checks both against the
    stationary law of the full chain (clamp atoms, Neumann reflection) computed numerically.
    """
    c = (length / cells) / math.sqrt(dt)
    p_c = math.erfc(c / math.sqrt(2))
    a = 1.0 - 0.5 * curvature * dt * (1.0 - p_c)
    v = dt * (1.0 - p_c - 2.0 * c * math.exp(-0.5 * c * c) / math.sqrt(2 * math.pi) + c * c * p_c)
    z = (np.linspace(0.0, length, cells + 1) - centre) / math.sqrt(2.0 * v / (1.0 - a * a))
    erfc = np.vectorize(math.erfc)
    lower, upper = 0.5 * erfc(-z), 0.5 * erfc(z)  # P(Y < edge) and P(Y > edge), each accurate in its own tail
    mass = np.where(z[1:] <= 0, lower[1:] - lower[:-1], upper[:-1] - upper[1:])
    return mass / mass.sum()


def clamped_step_cf(k: np.ndarray, dt: float, dx: float, nodes: int = 16) -> np.ndarray:
    r"""Characteristic function E[cos(k D)] of one clamped step ``D = clamp(√Δt Z, −Δx, Δx)``.

    The Gaussian part on (−Δx, Δx) by composite Gauss–Legendre quadrature, one panel of ``nodes``
    points per half-period of the fastest ``cos(k x)`` (exact to round-off), plus the two atoms
    ``P(|Z| > Δx/√Δt)/2`` at ±Δx.
    """
    s = math.sqrt(dt)
    k = np.asarray(k, dtype=np.float64)
    panels = max(1, math.ceil(float(np.abs(k).max(initial=0.0)) * 2 * dx / math.pi))
    u, w = np.polynomial.legendre.leggauss(nodes)
    edges = np.linspace(-dx, dx, panels + 1)
    half = 0.5 * (edges[1] - edges[0])
    x = (0.5 * (edges[:-1] + edges[1:])[:, None] + half * u[None, :]).ravel()
    dens = np.exp(-0.5 * (x / s) ** 2) / (s * math.sqrt(2 * math.pi)) * np.tile(w, panels) * half
    tail = math.erfc(dx / (s * math.sqrt(2)))  # P(|√Δt Z| > Δx)
    out = np.empty(k.shape)
    for i in range(0, k.size, 256):  # blocks of k keep the cos table small
        kk = k.ravel()[i:i + 256]
        out.ravel()[i:i + 256] = np.cos(np.multiply.outer(kk, x)) @ dens + tail * np.cos(kk * dx)
    return out


def cell_transition(cells: int, length: float, dt: float, steps: int, clamp: bool = True,
                    fold: int = 64) -> np.ndarray:
    r"""P[j, i]: probability that a particle started uniformly in cell j of a periodic 1D domain
    ends in cell i after ``steps`` steps of the walk the particle solvers take.

    Exact for i.i.d. increments with characteristic function φ (the clamped step of
    :func:`clamped_step_cf`; with ``clamp=False`` the Gaussian ``exp(−k²Δt/2)``): in Fourier
    series over the periodic domain, with ``k_m = 2πm/L`` and ``sinc(z) = sin z / z``,

    .. math:: P_{j→i} = \frac{Δx}{L} \sum_m \operatorname{sinc}^2(k_m Δx/2)\, φ(k_m)^n\, e^{i k_m (i−j) Δx},

    the n-fold convolution of the step done mode by mode. Modes ``|m| ≤ fold·cells`` are kept, or
    only those where ``exp(−n k²Δt/2) > 1e-20`` once the clamp's share of φ (at most
    ``2 erfc(Δx/√(2Δt))``) raised to the n is below 1e-16. Rows sum to 1; one step is exact to
    ~4e-6 (the series of a density with jumps), a few steps to round-off.
    """
    folded = walk_symbol(cells, length, dt, [steps], clamp, fold)[0]
    row = np.real(np.fft.ifft(folded))  # P as a function of d = i − j (cells·Δx/L = 1)
    d = (np.arange(cells)[None, :] - np.arange(cells)[:, None]) % cells
    return np.maximum(row[d], 0.0)


def walk_symbol(cells: int, length: float, dt: float, steps, clamp: bool = True, fold: int = 64) -> np.ndarray:
    r"""``P̂[i, m]``: the discrete Fourier transform over the ``cells`` cells of the periodic 1D
    transition row of :func:`cell_transition` after ``steps[i]`` steps,

    .. math:: \hat P_n(m) = \sum_{m' ≡ m \,(\mathrm{mod}\, M)} \operatorname{sinc}^2(k_{m'} Δx/2)\, φ(k_{m'})^n,

    the modes of the Fourier series folded onto the grid's M wave numbers (the same modes as
    :func:`cell_transition` keeps for the fewest steps asked). Real: the step is symmetric.
    """
    steps = np.atleast_1d(np.asarray(steps, dtype=np.int64))
    h = length / cells
    M = fold * cells
    n_min = int(steps.min())
    bound = 2 * math.erfc(h / math.sqrt(2 * dt)) if clamp else 0.0  # |φ(k)| ≤ exp(−k²Δt/2) + bound
    if n_min > 0 and bound**n_min < 1e-16:  # then modes past exp(−n k²Δt/2) = 1e-20 weigh nothing
        M = min(M, math.ceil(math.sqrt(2 * 20 * math.log(10) / (n_min * dt)) * length / (2 * math.pi)) + 1)
    m = np.arange(-M, M + 1)
    k = 2 * np.pi * m / length
    if clamp:  # φ is even: evaluate it on m ≥ 0
        phi = clamped_step_cf(k[m >= 0], dt, h)[np.abs(m)]
    else:
        phi = np.exp(-0.5 * k * k * dt)
    w = np.sinc(k * h / (2 * np.pi)) ** 2  # np.sinc(x) = sin(πx)/(πx)
    # e^{i k_m d Δx} depends on m mod cells only; no step: P̂ = 1 exactly (the sinc² series, cut)
    return np.stack([np.bincount(m % cells, w * phi**int(n), minlength=cells) if n else np.ones(cells)
                     for n in steps])


def particle_counts_periodic(ppc0: np.ndarray, lengths, dt: float, steps: int,
                             clamp: bool = True) -> dict[str, np.ndarray]:
    r"""Exact count moments per cell after ``steps`` walk steps for ``ppc0[j] = ℓ_j + α_j`` particles
    started uniformly in each cell j of a periodic box (any dimension), sampled as the solvers do
    (ℓ_j particles plus one with probability α_j).

    The walk's axes are independent, so a particle from cell j reaches cell i with probability
    ``p_ji = Π_a P_a[j_a, i_a]`` (:func:`cell_transition` per axis), and the count is a
    Poisson-binomial sum whose cumulants come from the power sums
    ``S_k(i) = Σ_j (ℓ_j + α_j^k) p_ji^k``, each a separable product over axes:
    κ1 = S1, κ2 = S1 − S2, κ3 = S1 − 3S2 + 2S3, κ4 = S1 − 7S2 + 12S3 − 6S4.
    """
    ppc0 = np.asarray(ppc0, dtype=np.float64)
    lengths = np.broadcast_to(np.asarray(lengths, dtype=np.float64), (ppc0.ndim,))
    P = [cell_transition(m, L, dt, steps, clamp) for m, L in zip(ppc0.shape, lengths)]
    ell = np.floor(ppc0)
    alpha = ppc0 - ell
    S = []
    for k in range(1, 5):
        s = ell + alpha**k
        for a, Pa in enumerate(P):  # contract source axis a with P_a^k, keeping the axis order
            s = np.moveaxis(np.tensordot(s, Pa**k, axes=([a], [0])), -1, a)
        S.append(s)
    S1, S2, S3, S4 = S
    return _from_cumulants(S1, S1 - S2, S1 - 3 * S2 + 2 * S3, S1 - 7 * S2 + 12 * S3 - 6 * S4)


def count_in_cells(ppc0: np.ndarray, P: np.ndarray, cells: np.ndarray) -> dict[str, float]:
    """Exact moments of the number of particles in the set ``cells`` (1D, transition matrix ``P``):
    a Poisson-binomial sum with ``p_j = Σ_{i ∈ cells} P[j, i]`` per particle."""
    p, repeats = _particles(P[:, cells].sum(1, keepdims=True), ppc0)
    p, r = p[:, 0], repeats
    q = 1.0 - p
    return {k: float(v) for k, v in _from_cumulants((r * p).sum(), (r * p * q).sum(), (r * p * q * (1 - 2 * p)).sum(),
                                                   (r * p * q * (1 - 6 * p * q)).sum()).items()}


def _particles(P: np.ndarray, ppc0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of per-particle probabilities and how many particles share each row: ℓ_j at P[j]
    and, where α_j > 0, one at α_j P[j]."""
    ppc0 = np.asarray(ppc0, dtype=np.float64)
    ell = np.floor(ppc0)
    alpha = ppc0 - ell
    frac = alpha > 0
    return np.vstack([P, alpha[frac, None] * P[frac]]), np.concatenate([ell, np.ones(frac.sum())]).astype(int)


def _mean_power(x: np.ndarray, steps) -> np.ndarray:
    """``x**n`` averaged over ``steps`` (an int, or the steps pooled into one row)."""
    steps = np.atleast_1d(np.asarray(steps, dtype=np.int64))
    return sum(x ** int(n) for n in steps) / steps.size


def linear_structure_factor(cells: tuple[int, ...], dt_over_dx2: tuple[float, ...], steps=None) -> np.ndarray:
    r"""Exact static structure factor of the linearised (Gaussian) scheme around a uniform density,
    on the grid's discrete wave numbers (the full DFT grid, numpy's FFT order; ``S[0] = 0``).

    S(k) = ⟨|δN̂_k|²⟩ / ⟨N_total⟩ with ``δN̂_k = Σ_j δN_j e^{−i k·x_j}`` the DFT of the cell counts'
    fluctuations (:mod:`ti_dk.core.spectra`). With the symbol of the discrete Laplacian
    ``λ(k) = Σ_a (4/Δx_a²) sin²(k_a Δx_a/2)`` and ``s_k = Δt λ(k)/4 = Σ_a (Δt/Δx_a²) sin²(π m_a/M_a)``,
    the Euler–Maruyama step of eq. (10)–(11) (D = ½) multiplies mode k by ``g_k = 1 − 2 s_k`` and
    adds noise of variance ``4 ρ s_k`` per cell and step (ρ particles per cell: each face carries a
    count of variance ρ Δt/Δx_a², and ``|1 − e^{−i k_a Δx_a}|² = 4 sin²(k_a Δx_a/2)``). So
    ``⟨|δN̂_k|²⟩/(M ρ) = 4 s_k Σ_{i<n} g_k^{2i}``:

    .. math:: S_n(k) = \frac{1 − g_k^{2n}}{1 − s_k} \xrightarrow{n→∞} \frac{1}{1 − Δt λ(k)/4},

    after n steps from the uniform state (``steps = n``; a sequence of steps: their mean, a pooled
    row), or stationary (``steps`` None). Independent of ρ; S → 1 as Δt → 0 (the particles'
    answer); k = 0 (the total) is exactly 0. Parseval gives the sum rule
    ``ρ · mean_k S(k)`` = the per-cell count variance (:func:`linear_scheme_variance`).
    """
    grids = np.meshgrid(*[np.arange(m) for m in cells], indexing="ij")
    s = sum(c * np.sin(np.pi * k / m) ** 2 for c, k, m in zip(dt_over_dx2, grids, cells))
    S = 1.0 / (1.0 - s)
    if steps is not None:
        S = S * (1.0 - _mean_power((1.0 - 2.0 * s) ** 2, steps))
    S.flat[0] = 0.0
    return S


def linear_scheme_variance(cells: tuple[int, ...], dt_over_dx2: tuple[float, ...], ppc: float,
                           steps: int | None = None) -> float:
    r"""Exact per-cell count variance of the linearised (Gaussian) scheme around a uniform density.

    Mode k of the discrete Fourier transform has amplification g_k = 1 − 2 S_k and, in count units,
    noise variance 4 λ S_k per step, with S_k = Σ_a (Δt/Δx_a²) sin²(π k_a / M_a). Its stationary
    variance is λ / (1 − S_k); started from the uniform state it is λ (1 − g_k^{2n}) / (1 − S_k)
    after n steps. The cell variance is the mean over all modes, the k = 0 mode (total mass) being
    exactly zero: λ (1 − 1/M) · mean_{k≠0} 1/(1 − S_k) in the stationary case — λ times the mean
    of :func:`linear_structure_factor`.
    """
    return float(ppc * linear_structure_factor(cells, dt_over_dx2, steps).mean())


def particle_structure_factor(ppc: float, cells: tuple[int, ...], lengths, dt: float, steps=None,
                              clamp: bool = True) -> np.ndarray:
    r"""Exact static structure factor of the particle counts in a periodic box (full DFT grid,
    numpy's FFT order), defined as in :func:`linear_structure_factor`.

    ``steps`` None: N independent particles uniform in the box (``particle_init =
    "exact_uniform"``, and the equilibrium of any start): ``S = 1`` for k ≠ 0 and 0 at k = 0 (N is
    fixed). Otherwise ``ppc = ℓ + α`` particles started uniformly in each cell (ℓ, plus one with
    probability α), after n steps of the walk: each particle adds ``Var e^{−ik·x} = 1 − |E e^{−ik·x}|²``
    to ⟨|δN̂_k|²⟩ (a Bernoulli one ``α − α²|…|²``), and ``|E e^{−ik·x}| = |P̂_n(k)|``, the product
    over axes of :func:`walk_symbol`:

    .. math:: S_n(k) = \frac{ℓ + α − (ℓ + α²)\, |\hat P_n(k)|^2}{ℓ + α},

    which tends to 1 (k ≠ 0) and to α(1 − α)/(ℓ + α) at k = 0. A sequence of steps: their mean.
    """
    cells = tuple(cells)
    S = np.ones(cells)
    if steps is None:
        S.flat[0] = 0.0
        return S
    lengths = np.broadcast_to(np.asarray(lengths, dtype=np.float64), (len(cells),))
    ell = math.floor(ppc)
    alpha = ppc - ell
    hats = [walk_symbol(m, L, dt, steps, clamp) for m, L in zip(cells, lengths)]  # (steps, M_a) per axis
    p2 = np.zeros(cells)
    for i in range(hats[0].shape[0]):
        p2 += math.prod(np.ix_(*[h[i] for h in hats])) ** 2  # |P̂_n(k)|², separable over axes
    p2 /= hats[0].shape[0]
    return (ell + alpha - (ell + alpha**2) * p2) / ppc


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


def void_reference(ppc0: np.ndarray, length: float, dt: float, steps: int, members: int, cells: np.ndarray,
                   replicas: int = 200) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The exact per-cell moments of particle counts after ``steps`` clamped steps from the initial
    counts ``ppc0`` (periodic 1D, :func:`particle_counts_periodic`), and the sampling standard
    errors of an ensemble of ``members`` in the ``cells`` asked for (NaN elsewhere)."""
    exact = particle_counts_periodic(ppc0, length, dt, steps)
    p, repeats = _particles(cell_transition(len(ppc0), length, dt, steps), ppc0)
    se = {k: np.full(len(ppc0), np.nan) for k in exact}
    for i in np.flatnonzero(cells):
        for k, v in sampling_se(poisson_binomial_pmf(p[:, i], repeats), members, replicas, seed=int(i)).items():
            se[k][i] = v
    return exact, se


def _fine_step(cells: int, sub: int, length: float, dt: float, nodes: int = 64) -> np.ndarray:
    """One clamped step on ``cells · sub`` periodic sub-bins: ``K[d]``, the probability that a particle
    uniform in a sub-bin ends ``d`` sub-bins away (``d`` mod the sub-bin count)."""
    h, dx, s = length / (cells * sub), length / cells, math.sqrt(dt)
    erf = np.vectorize(math.erf)

    def cdf(x):  # of D = clamp(√Δt Z, −Δx, Δx): atoms at ±Δx
        return np.where(x < -dx, 0.0, np.where(x >= dx, 1.0, 0.5 * (1.0 + erf(x / (s * math.sqrt(2))))))

    start = (np.arange(nodes) + 0.5) / nodes * h  # midpoints over the source sub-bin
    d = np.arange(-sub - 1, sub + 2)
    K = np.zeros(cells * sub)
    K[d % K.size] = (cdf((d[:, None] + 1) * h - start) - cdf(d[:, None] * h - start)).mean(axis=1)
    return K


def hybrid_mean_1d(ppc0: np.ndarray, region: np.ndarray, dt: float, steps: int, length: float = 1.0,
                   ghost_profile: str = "mean", sub: int = 128) -> np.ndarray:
    r"""Expected particles per cell of the hybrid (:class:`ti_dk.hybrid.solver.HybridSolver`, periodic 1D,
    the particle region ``region`` fixed, one particle step per SPDE step) after ``steps`` steps:
    the exact mean of the *algorithm*, beside the exact mean of the particles
    (:func:`particle_counts_periodic`); their difference is the coupling's own bias.

    Every part of a hybrid step is linear in expectation, so the mean follows one deterministic
    pass of the step: the FV mean ``Q`` of eq. (9) without noise (E Z = 0) outside the region; the
    region's particles as a density on ``sub`` sub-bins per cell, moved by the exact clamped step;
    ghosts of each ring cell ``c``: ``Q_c`` particles on the profile :meth:`ti_dk.hybrid.incell.InCell.tilt`
    gives (``mean``: slope of q̄ = the same FV mean run from the start on the whole grid; uniform
    at the first step or with ``uniform``); S1 drops the FV fluxes across ring–region faces, the
    covered cells take the expected counts, ring cells gain ΔN (eq. 12). Exact while ghost cells
    hold positive densities (E max(q, 0) = E q) and the ghost-entry cap does not bind; sub-bins
    add a spread of (Δx/sub)²/12 per step (relative error ~1e-4 at ``sub = 128``).
    """
    if ghost_profile not in ("mean", "uniform"):
        raise ValueError("the mean is linear for ghost_profile 'mean' and 'uniform' only")
    ppc0, cov = np.asarray(ppc0, dtype=np.float64), np.asarray(region, dtype=bool)
    M, c = ppc0.size, dt * (ppc0.size / length) ** 2  # C = Δt/Δx²
    ring = ~cov & (np.roll(cov, 1) | np.roll(cov, -1))
    fine_cov = np.repeat(cov, sub)
    K = _fine_step(M, sub, length, dt)
    fK = np.fft.rfft(K)
    walk = lambda g: np.fft.irfft(np.fft.rfft(g) * fK, M * sub)  # noqa: E731
    u = (np.arange(sub) + 0.5) / sub
    to_next = np.array([K[(np.arange(sub, 2 * sub) - s)].sum() for s in range(sub)])  # bin s → cell c+1
    to_prev = to_next[::-1]
    fv = lambda q: q + 0.5 * c * (np.roll(q, 1) - 2 * q + np.roll(q, -1))  # noqa: E731  eq. (9), E Z = 0
    Q, qbar = ppc0.copy(), ppc0.copy()
    f = np.repeat(ppc0 * cov, sub) / sub  # the region's first particles lie uniformly in their cells
    for n in range(steps):
        ghosts, dN = np.zeros((M, sub)), np.zeros(M)
        for i in np.flatnonzero(ring):
            b = 0.0
            if ghost_profile == "mean" and n > 0 and qbar[i] > 0:
                b = np.clip((qbar[(i + 1) % M] - qbar[i - 1]) / (2 * qbar[i]), -2.0, 2.0)
            shape = 1.0 + b * (u - 0.5)
            ghosts[i] = Q[i] * shape / shape.sum()
            dN[i] -= ghosts[i] @ (to_next * cov[(i + 1) % M] + to_prev * cov[i - 1])  # ghosts that enter
        Qs = fv(Q)
        for i in np.flatnonzero(ring):  # S1: no FV flux across faces with covered cells
            Qs[i] -= 0.5 * c * ((Q[i - 1] - Q[i]) * cov[i - 1] + (Q[(i + 1) % M] - Q[i]) * cov[(i + 1) % M])
        moved = walk(f)
        dN += (moved * ~fine_cov).reshape(M, sub).sum(axis=1) * ring  # particles the region gave
        f = (moved + walk(ghosts.ravel())) * fine_cov
        Q, qbar = Qs + dN, fv(qbar)
        Q[cov] = f.reshape(M, sub).sum(axis=1)[cov]
    return Q


def walk_crossing_fraction(u_prime, start: np.ndarray, dt: float, times, split: float = 0.5, length: float = 1.0,
                           sub: int = 256) -> np.ndarray:
    """Exact mean share ``f(t) = N_R / N`` of the 1D particle method's particles beyond ``x = split``
    in a potential, Dirichlet walls at density 0 (a particle stepping past one is gone), no sampling.

    The start ``start`` (particles, or shares, per cell; uniform within each cell, as the
    particles are placed) on ``sub`` bins a cell is moved by the Euler–Maruyama step's exact
    kernel: from a bin centre x, a Gaussian of variance Δt about ``x − ½U'(x)Δt`` integrated over
    each bin (a sparse transition matrix). The clamp at ±Δx is left out (its probability,
    ``erfc((Δx − |½U'|Δt)/√(2Δt))``, is ≈ 1e-12 for the double well at 32 cells and C = 0.02).
    ``u_prime``: the NumPy-vectorised U'(x) [kT/L]; ``times``: where f is taken (multiples of Δt).
    Compared with the particles in ``benchmarks/kramers1d.py`` (rate 0.1120 at 32 cells, C = 0.02)."""
    import scipy.sparse as sparse
    from scipy.special import ndtr

    start = np.asarray(start, dtype=np.float64)
    M = start.size * sub
    d = length / M
    xs = (np.arange(M) + 0.5) * d
    mu = xs - 0.5 * u_prime(xs) * dt
    reach = sub + 1  # bins a step may cross: the walk clamps it to ±Δx
    rows, cols, vals = [], [], []
    for k in range(-reach, reach + 1):
        j = np.arange(M) + k
        ok = (j >= 0) & (j < M)  # beyond a wall: absorbed
        p = ndtr((xs + (k + 0.5) * d - mu) / math.sqrt(dt)) - ndtr((xs + (k - 0.5) * d - mu) / math.sqrt(dt))
        rows.append(j[ok]), cols.append(np.arange(M)[ok]), vals.append(p[ok])
    T = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(M, M))
    p, n, right, out = np.repeat(start, sub) / sub, 0, xs > split, []
    for t in times:
        while n < round(t / dt):
            p, n = T @ p, n + 1
        out.append(p[right].sum() / p.sum())
    return np.array(out)
