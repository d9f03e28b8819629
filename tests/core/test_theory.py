"""The exact answers themselves, checked by independent routes."""
import math

import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.core import theory


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


def test_fixed_and_poisson_moments_match_the_convolved_pmf():
    n, lam, p = 7, 2.5, 0.3
    binom = theory.poisson_binomial_pmf(np.array([p]), np.array([n]))
    k = np.arange(60)
    poisson = np.exp(-lam * p + k * math.log(lam * p) - np.array([math.lgamma(j + 1) for j in k]))
    pmf = np.convolve(binom, poisson)[:60]
    mean = (k * pmf).sum()
    c = k - mean
    var = (c**2 * pmf).sum()
    m = theory.fixed_and_poisson_moments(n, lam, p)
    assert np.isclose(m["mean"], mean) and np.isclose(m["variance"], var)
    assert np.isclose(m["skewness"], (c**3 * pmf).sum() / var**1.5)
    assert np.isclose(m["kurtosis"], (c**4 * pmf).sum() / var**2)


def _phi(z):
    return math.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)


def _Q(z):
    return 0.5 * math.erfc(z / math.sqrt(2))


def test_cell_transition_is_stochastic_and_diffusive():
    dt, n = 0.001 / 40, 40
    P = theory.cell_transition(50, 1.0, dt, n, clamp=False)
    assert np.allclose(P.sum(axis=1), 1.0) and np.allclose(P, P.T)
    x = (np.arange(50) - 25) * 0.02
    # spread of the end cell: start uniform in the cell (h²/12) plus diffusion t, plus the
    # end-cell discretisation h²/12
    assert np.isclose((P[25] * x**2).sum(), 0.001 + 2 * 0.02**2 / 12, rtol=1e-3)
    # and the closed form of the Gaussian: (G(d+h) − 2G(d) + G(d−h))/h, G(x) = x Φ(x/s) + s φ(x/s)
    s, h = math.sqrt(dt * n), 0.02

    def G(x):
        return x * (1 - _Q(x / s)) + s * _phi(x / s)

    for d in range(4):
        exact = (G((d + 1) * h) - 2 * G(d * h) + G((d - 1) * h)) / h
        assert abs(P[25, 25 + d] - exact) < 1e-12


def test_clamped_step_is_the_truncated_normal_with_atoms():
    dt, h = 0.125 * 0.01**2, 0.01
    s, a = math.sqrt(dt), 0.01 / math.sqrt(dt)
    # variance of clamp(√Δt Z, −Δx, Δx): Δt (1 − 2aφ(a) − 2Q(a)) + 2Δx² Q(a)  (0.9914 Δt at C = 1/8)
    var = dt * (1 - 2 * a * _phi(a) - 2 * _Q(a)) + 2 * h * h * _Q(a)
    k = 1e-3 / h  # 2(1 − φ(k))/k² = Var − k² E[D⁴]/12 + …
    assert math.isclose(2 * (1 - theory.clamped_step_cf(np.array([k]), dt, h)[0]) / k**2, var, rel_tol=1e-6)
    assert 0.99 < var / dt < 0.992
    # one step from uniform in a cell: P(cross a face) = E[max(D, 0)] / Δx
    P1 = theory.cell_transition(100, 1.0, dt, 1)
    cross = (s / math.sqrt(2 * math.pi) * (1 - math.exp(-0.5 * a * a)) + h * _Q(a)) / h
    assert abs(P1[10, 11] - cross) < 1e-5 and abs(P1[10, 9] - cross) < 1e-5
    # two steps: direct convolution of the binned step density on a fine grid
    K = 400
    u = np.linspace(-h, h, 2 * K + 1)
    cdf = np.array([1 - _Q(v / s) for v in u])
    step = np.diff(cdf)  # fine cells of width h/K between −h and h
    step = np.concatenate([[_Q(a)], np.zeros(0), step, [_Q(a)]])  # atoms at ±h (ends of the grid)
    start = np.full(K, 1.0 / K)
    two = np.convolve(np.convolve(start, step), step)  # fine positions from −2h − … on
    offset = -2 * K - 1  # fine index of the first entry relative to the cell's lower face
    cells = (np.arange(two.size) + offset) // K
    P2 = theory.cell_transition(100, 1.0, dt, 2)[10]
    for c in (-2, -1, 0, 1, 2):
        assert abs(two[cells == c].sum() - P2[(10 + c) % 100]) < 2e-3 / K * 10, c


def test_counts_in_2d_are_the_sum_over_particles():
    # brute force over every (source cell, particle) of a small periodic box
    ppc0 = np.array([[0.0, 2.5, 1.0], [3.0, 0.0, 0.5], [1.0, 1.0, 0.0], [0.0, 4.0, 2.0]])
    dt, steps = 0.1 * 0.25**2, 7
    Px = theory.cell_transition(4, 1.0, dt, steps)
    Py = theory.cell_transition(3, 0.75, dt, steps)
    got = theory.particle_counts_periodic(ppc0, (1.0, 0.75), dt, steps)
    for i in np.ndindex(ppc0.shape):
        p, reps = [], []
        for j in np.ndindex(ppc0.shape):
            pj = Px[j[0], i[0]] * Py[j[1], i[1]]
            ell = int(ppc0[j])
            p += [pj, (ppc0[j] - ell) * pj]
            reps += [ell, 1]
        m = theory.poisson_binomial_moments(np.repeat(p, reps))
        for k in m:
            assert np.isclose(got[k][i], m[k], rtol=1e-10), (k, i)


def test_linear_scheme_variance_limits():
    # C → 0 gives the binomial variance λ(1 − 1/M); many steps reach the stationary value
    assert np.isclose(theory.linear_scheme_variance((100,), (1e-9,), 5.0), 5.0 * 0.99)
    assert np.isclose(theory.linear_scheme_variance((10,), (0.1,), 5.0, steps=100000),
                      theory.linear_scheme_variance((10,), (0.1,), 5.0))
    assert theory.linear_scheme_variance((10,), (0.1,), 5.0, steps=0) == 0.0


def _laplacian(m):
    """The periodic 1D second-difference matrix (−2 on the diagonal)."""
    eye = np.eye(m)
    return np.roll(eye, 1, 0) + np.roll(eye, -1, 0) - 2 * eye


@pytest.mark.parametrize("cells, c", [((10,), (0.3,)), ((4, 6), (0.05, 0.2))])
def test_linear_structure_factor_is_the_fourier_form_of_the_real_space_covariance(cells, c):
    """Independent route: the cell counts' covariance iterated in real space, Cov ← A Cov Aᵀ + Q with
    A = 1 + ½ Σ_a c_a L_a (eq. 10 at D = ½, c_a = Δt/Δx_a²) and Q = ρ Σ_a c_a (−L_a) (each face a
    count of variance ρ c_a); its DFT's diagonal over ρ M is S(k), and its diagonal's mean is the
    per-cell variance (the sum rule)."""
    rho, steps, M = 3.0, 40, math.prod(cells)
    eyes = [np.eye(m) for m in cells]
    lap = []
    for a, m in enumerate(cells):
        op = np.ones((1, 1))
        for b, e in enumerate(eyes):
            op = np.kron(op, _laplacian(m) if b == a else e)
        lap.append(op)
    A = np.eye(M) + 0.5 * sum(ca * La for ca, La in zip(c, lap))
    Q = -rho * sum(ca * La for ca, La in zip(c, lap))
    cov = np.zeros((M, M))
    for _ in range(steps):
        cov = A @ cov @ A.T + Q
    F = np.fft.fftn(np.eye(M).reshape(M, *cells), axes=tuple(range(1, len(cells) + 1))).reshape(M, M)
    S = np.real(np.einsum("jk,jl,lk->k", F.conj(), cov, F)).reshape(cells) / (rho * M)
    assert np.allclose(theory.linear_structure_factor(cells, c, steps), S, rtol=1e-12, atol=1e-12)
    assert np.isclose(theory.linear_scheme_variance(cells, c, rho, steps), np.diag(cov).mean(), rtol=1e-12)


def test_linear_structure_factor_limits():
    """Δt → 0: the particles' S = 1 (k ≠ 0), off by ≈ s_k ≤ Σ_a c_a; S(0) = 0; no steps: 0; a
    pooled row is the mean over its steps; many steps: the stationary 1/(1 − s_k)."""
    for c in (1e-3, 1e-6):
        S = theory.linear_structure_factor((16, 12), (c, 2 * c))
        assert S.flat[0] == 0 and np.allclose(S.flat[1:], 1.0, atol=4 * c, rtol=0)
    S = theory.linear_structure_factor((16,), (0.3,))
    assert np.isclose(S[8], 1 / (1 - 0.3))  # the Nyquist mode: s = c
    assert not np.any(theory.linear_structure_factor((16,), (0.3,), 0))
    pooled = theory.linear_structure_factor((16,), (0.3,), range(5, 30, 4))
    assert np.allclose(pooled, np.mean([theory.linear_structure_factor((16,), (0.3,), n) for n in range(5, 30, 4)], 0))
    assert np.allclose(theory.linear_structure_factor((16,), (0.3,), 100000), S)


@pytest.mark.parametrize("cells, lengths, ppc", [((12,), (1.0,), 2.3), ((6, 8), (1.0, 2.0), 3.0)])
def test_particle_structure_factor_sum_rule_and_limits(cells, lengths, ppc):
    """ρ · mean_k S_n(k) is the per-cell variance of the Poisson-binomial counts (a different route:
    cumulants of the transition probabilities in real space); S(0) = α(1 − α)/ρ, the total's
    Bernoulli variance; step 0: nothing has moved; many steps: 1 for k ≠ 0."""
    dt = 0.1 * (lengths[0] / cells[0]) ** 2
    alpha = ppc - math.floor(ppc)
    for n in (1, 5, 40):
        S = theory.particle_structure_factor(ppc, cells, lengths, dt, n)
        var = theory.particle_counts_periodic(np.full(cells, ppc), lengths, dt, n)["variance"]
        assert np.isclose(ppc * S.mean(), var.mean(), rtol=1e-9)
        assert np.isclose(S.flat[0], alpha * (1 - alpha) / ppc, rtol=1e-9, atol=1e-12)
    assert np.allclose(theory.particle_structure_factor(ppc, cells, lengths, dt, 0), alpha * (1 - alpha) / ppc,
                       rtol=0, atol=1e-15)
    late = theory.particle_structure_factor(ppc, cells, lengths, dt, 20000)
    assert np.allclose(late.flat[1:], 1.0, atol=1e-9)
    uniform = theory.particle_structure_factor(ppc, cells, lengths, dt)
    assert uniform.flat[0] == 0 and np.all(uniform.flat[1:] == 1)


def test_hybrid_mean_reduces_to_its_two_methods_and_conserves_mass():
    M, C, steps = 40, 0.125, 60
    dt = C / M**2
    ppc0 = np.full(M, 12.5)
    ppc0[15:25] = 0.0
    exact = theory.particle_counts_periodic(ppc0, 1.0, dt, steps)["mean"]
    all_particles = theory.hybrid_mean_1d(ppc0, np.ones(M, bool), dt, steps)
    assert np.abs(all_particles - exact).max() < 2e-4  # sub-bin spread only
    q = ppc0.copy()
    for _ in range(steps):
        q = q + 0.5 * C * (np.roll(q, 1) - 2 * q + np.roll(q, -1))
    assert np.allclose(theory.hybrid_mean_1d(ppc0, np.zeros(M, bool), dt, steps), q, rtol=0, atol=1e-12)
    region = np.zeros(M, bool)
    region[14:26] = True
    for profile in ("mean", "uniform"):
        h = theory.hybrid_mean_1d(ppc0, region, dt, steps, ghost_profile=profile)
        assert abs(h.sum() - ppc0.sum()) < 1e-9
    # uniform ghosts overfill the first covered cells and drain the ring (benchmarks/RESULTS.md)
    assert h[14] - exact[14] > 0.05 and h[13] - exact[13] < -0.05


def _walk_law_numerically(cells, dt, k, m):
    """Cell shares of the stationary law of the chain the particles run in the trap U = ½k(x − ½)²
    on [0, 1] with Neumann walls: x ← reflect(x + clamp(−½U'(x)Δt + √Δt Z, ±Δx)), the drift inside
    the clamp, the clamp's atoms at ±Δx. Nyström: the density π at the nodes x_j = jΔx/m obeys
    π(y) = ∫ π(x) K(x, y) dx + the atoms (π(y ∓ Δx) P(clamp at ±Δx)), K the Gaussian part with its
    reflected images; the trapezoid rule on the nodes (weight ½ where K jumps, at |y − x| = Δx:
    error O(h²), removed by the caller's Richardson step), π by inverse iteration."""
    dx, s = 1.0 / cells, math.sqrt(dt)
    h, n = dx / m, cells * m
    x = np.arange(n + 1) * h
    w = np.full(n + 1, h)
    w[[0, -1]] = h / 2
    mu = -0.5 * k * (x - 0.5) * dt
    A = np.zeros((n + 1, n + 1))  # A[j, i]: density at x_j from the node x_i
    for y in (x, -x, 2.0 - x):  # the walls' images
        d = y[:, None] - x[None, :]
        inside = np.where(np.abs(np.abs(d) - dx) < 1e-9 * h, 0.5, (np.abs(d) < dx) * 1.0)
        A += inside * w * np.exp(-0.5 * ((d - mu) / s) ** 2) / (s * math.sqrt(2 * math.pi))
    erfc = np.vectorize(math.erfc)
    for sign in (1, -1):  # the atoms: x_i → x_i ± Δx, reflected at the walls (node to node)
        j = np.arange(n + 1) + sign * m
        j = np.where(j < 0, -j, np.where(j > n, 2 * n - j, j))
        np.add.at(A, (j, np.arange(n + 1)), 0.5 * erfc((dx - sign * mu) / (s * math.sqrt(2))))
    pi = np.exp(-0.5 * k * (x - 0.5) ** 2)  # from e^{−U}: A's top eigenvalue is 1 − O(h²), the next
    for _ in range(3):  # 1 − O(kΔt): each step of inverse iteration at 1 shrinks the error by ~1e-3
        pi = np.linalg.solve(A - np.eye(n + 1), pi)
        pi /= pi.sum()
    shares = np.array([np.trapezoid(pi[c * m:(c + 1) * m + 1], dx=h) for c in range(cells)])
    return shares / shares.sum()


def test_the_trap_walk_law_is_the_clamped_chains_stationary_law():
    """trap_walk_shares (AR(1), linear in the drift, no walls) against the full chain's stationary
    law computed numerically (Richardson-extrapolated in the node spacing: two extrapolations
    agree), in units of the standard error of a cell's mean count in the slow hybrid test of
    tests/hybrid/test_solver.py (trap1d: N = 400, 10⁵ members). The Boltzmann shares differ by
    more than an SE there: the walk's own law is what 10⁵ members can tell apart."""
    cells, dt, k, N, M = 40, 0.0625 / 40**2, 1 / 0.08**2, 400, 100_000
    law = {m: _walk_law_numerically(cells, dt, k, m) for m in (6, 8, 12, 16)}
    exact, check = (4 * law[16] - law[8]) / 3, (4 * law[12] - law[6]) / 3
    se = np.sqrt(N * exact * (1 - exact) / M)
    assert np.abs(N * (check - exact) / se).max() < 3e-3
    ar1 = theory.trap_walk_shares(cells, 1.0, dt, k, 0.5)
    assert np.abs(N * (ar1 - exact) / se).max() < 5e-3
    boltzmann = load_scene("trap1d").potential.boltzmann_weights((cells,), (1.0,))
    assert np.abs(N * (boltzmann - exact) / se).max() > 1
