"""The bias of one ensemble's per-cell moments against another's, with standard errors from the
samples themselves: what :mod:`ti_dk.control.tradeoff` reports for every candidate setting.

Samples come as ``x[s, m, cell]``: ``s`` the samples a member gives to one statistics row (one, or
several pooled steps of a stationary scene), ``m`` the members (independent), ``cell`` any cells.
The moments are those of :class:`ti_dk.core.stats.Moments` (mean, unbiased variance, skewness
μ₃/μ₂^{3/2}, non-excess kurtosis μ₄/μ₂²). Their standard errors come from the influence function
of each moment (the delta method; it takes the sample central moments up to the 8th),
summed within a member and varied across members, so the correlated samples of one member count
once:

    SE² = M/(M − 1) · Σ_m (Σ_s IF(x_sm))² / n²,   n = S·M,

which for one sample a member is the familiar (1/n)·mean IF², e.g. (μ₄ − μ₂²)/n for the variance.

A candidate's bias over the cells and times asked for is summarised per moment as the root mean
square of the per-cell biases b_i, its noise taken off: each ensemble is split in two halves of
members, and the product of the halves' biases b_A,i · b_B,i (independent noises) estimates b_i²
without the noise (b_i² − s_i² with delta-method s_i² leaves the skewness's and kurtosis's SE
underestimated by 10–20 % at a few hundred members, which reads as a bias). So a method without bias
scores 0 on average, not its noise:

- ``bias``: √(mean_i b_A,i b_B,i), in the moment's own units (particles per cell for the mean);
- ``rel``: √(Σ_i b_A,i b_B,i / Σ_i r_i²), relative to the reference values r_i;
- ``z``: √(mean_i b_A,i b_B,i / σ_i²), in standard errors σ_i = SE_ref,i · √(M_ref / N) of the
  reference method at the planned ensemble N (the bias a run of N members shows against its noise).

Each summary's own standard error comes from the same per-member noises (:func:`_square`), so it
holds the correlations between cells and between times (the same members at every time).
"""
from __future__ import annotations

import numpy as np

MOMENTS = ("mean", "variance", "skewness", "kurtosis")
SUMMARIES = ("bias", "rel", "z")


def moments(x: np.ndarray, members: bool = False) -> tuple[dict, dict] | tuple[dict, dict, dict]:
    """Per-cell moments of ``x[s, m, ...]`` and their standard errors (module docstring); with
    ``members``, also each moment's noise as a sum over members, ``u[m, ...]`` (estimate − truth ≈
    Σ_m u[m], to first order; the SE is √Σ_m u[m]²)."""
    x = np.asarray(x, dtype=np.float64)
    S, M = x.shape[:2]
    n = S * M
    mean = x.mean(axis=(0, 1))
    d = x - mean
    mu = {p: (d**p).mean(axis=(0, 1)) for p in (2, 3, 4)}
    with np.errstate(divide="ignore", invalid="ignore"):
        skew, kurt = mu[3] / mu[2] ** 1.5, mu[4] / mu[2] ** 2
        i2 = d**2 - mu[2]
        i3 = d**3 - mu[3] - 3 * mu[2] * d
        i4 = d**4 - mu[4] - 4 * mu[3] * d
        infl = {"mean": d, "variance": i2 * n / (n - 1),
                "skewness": i3 / mu[2] ** 1.5 - 1.5 * skew * i2 / mu[2],
                "kurtosis": i4 / mu[2] ** 2 - 2 * kurt * i2 / mu[2]}
    value = {"mean": mean, "variance": mu[2] * n / (n - 1), "skewness": skew, "kurtosis": kurt}
    u = {k: v.sum(axis=0) * np.sqrt(M / (M - 1)) / n for k, v in infl.items()}  # per member
    se = {k: np.sqrt((v**2).sum(axis=0)) for k, v in u.items()}
    return (value, se, u) if members else (value, se)


def halves(members: int) -> tuple[np.ndarray, np.ndarray]:
    """The two halves of the members: even and odd ones."""
    return np.arange(0, members, 2), np.arange(1, members, 2)


class Ensemble:
    """One ensemble's rows of samples ``[x[s, m, cell] for each row]``: its per-cell moments and
    standard errors (``whole``, a pair of dicts of ``(rows, *cells)`` arrays) and those of its two
    halves with their per-member noise (``halves``, triples, the noise ``(members, rows, *cells)``)."""

    def __init__(self, rows: list[np.ndarray]):
        self.members = rows[0].shape[1]
        if self.members < 4:
            raise ValueError("a pilot needs at least 4 members (two halves of two)")
        self.whole = self._at(rows, np.arange(self.members))
        self.halves = [self._at(rows, h, True) for h in halves(self.members)]

    @staticmethod
    def _at(rows: list[np.ndarray], members: np.ndarray, noise: bool = False) -> tuple:
        per_row = [moments(r[:, members], noise) for r in rows]
        return tuple({k: np.stack([p[j][k] for p in per_row], axis=j // 2) for k in MOMENTS}
                     for j in range(len(per_row[0])))


def _square(bias_a, bias_b, noise_a, noise_b, w) -> tuple[float, float]:
    """θ = Σ_i w_i b_A,i b_B,i and its SE: the two halves' noises are independent, so
    Var θ = Σ_m (Σ_i w_i b_B,i u_A,mi)² + (the same with A, B swapped) − Σ_mm' (Σ_i w_i u_A,mi u_B,m'i)²
    (each plug-in b_B = b + noise counts the noise-by-noise term once more)."""
    ua, ub = (u.reshape(len(u), -1) for u in (noise_a, noise_b))
    theta = float((w * bias_a * bias_b).sum())
    quad = float((((ua * w) @ ub.T) ** 2).sum())
    lin = float(((ua @ (w * bias_b)) ** 2).sum() + ((ub @ (w * bias_a)) ** 2).sum())
    return theta, float(np.sqrt(max(lin - quad, quad)))


def compare(cand: Ensemble, ref: Ensemble, planned: int, cells: np.ndarray) -> dict:
    """Every summary of ``cand``'s bias against ``ref`` over ``cells`` (a mask over rows × cells),
    as its square with that square's standard error: ``{(moment, summary): (value², SE)}``."""
    if cand is ref:
        return {(k, s): (0.0, 0.0) for k in MOMENTS for s in SUMMARIES}
    out = {}
    count = int(cells.sum())
    for k in MOMENTS:
        b, u = [], []
        for (cv, _, cu), (rv, _, ru) in zip(cand.halves, ref.halves):
            b.append((cv[k] - rv[k])[cells])
            u.append(np.concatenate([cu[k][:, cells], -ru[k][:, cells]]))
        sigma2 = (ref.whole[1][k] ** 2 * ref.members / planned)[cells]
        weights = {"bias": np.full(count, 1.0 / count),
                   "rel": np.full(count, 1.0 / (ref.whole[0][k][cells] ** 2).sum()), "z": 1.0 / (count * sigma2)}
        for s, w in weights.items():
            out[k, s] = _square(b[0], b[1], u[0], u[1], w)
    return out


def differ(a: tuple[float, float], b: tuple[float, float], z: float = 2.0) -> bool:
    """Whether two summaries ``(value², SE)`` are told apart: more than ``z`` SEs of their difference
    (the SEs combined as independent, which overstates it when both are measured against the same
    reference: the safe side)."""
    return abs(a[0] - b[0]) > z * np.hypot(a[1], b[1])


def root(square: float, se: float) -> tuple[float, float, float]:
    """A summary from its square and that square's SE: ``(value, low, high)``, the value √max(0, v²)
    and the one-SE band √max(0, v² ∓ SE)."""
    return tuple(float(np.sqrt(max(0.0, square + d))) for d in (0.0, -se, se))


def usable(ref: Ensemble, cand: list[Ensemble], cells: np.ndarray) -> np.ndarray:
    """``cells`` where every moment and SE of every ensemble is finite and the reference varies."""
    ok = cells & (ref.whole[1]["variance"] > 0)
    for e in (ref, *cand):
        for part in (*e.whole, *(h[j] for h in e.halves for j in (0, 1))):
            for v in part.values():
                ok &= np.isfinite(v)
    return ok
