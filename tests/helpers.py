"""Helpers shared by several test modules: count moments against exact ones, commands as a user runs them."""
import math
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


def trap_tails(method: str, members: int, t_end: float, cells: int = 40):
    """Issue 28's check of the harmonic trap's tails: ``trap1d`` (Neumann, σ = 0.08, C = 1/16,
    N = 400) with ``members`` members and one statistics row at ``t_end`` (one sample a member: the
    samples are independent), the hybrid's region fixed (``regrid_interval = 0``) where the start
    holds fewer than ``threshold`` particles per cell, plus the buffer. Returns the scene, the
    covered cells, the content ``n`` the start fixes and the mean ``lam`` of the Poisson number of
    particles it samples (the hybrid samples the covered cells; the particle method places
    exactly N), and the walk's stationary shares (:func:`theory.trap_walk_shares`, U'' read off
    the scene's potential by a central difference, exact for a quadratic)."""
    from ti_dk import load_scene
    from ti_dk.core import theory
    from ti_dk.hybrid import clustering

    scene = load_scene("trap1d", method=method, cells=[cells], ppc=400 / cells, t_end=t_end, ensemble=members,
                       t_equil=None, output_times=[], regrid_interval=0)
    covered = np.flatnonzero(clustering.region(scene.initial_ppc, scene.hybrid.regrid, (False,))[1])
    lam = float(scene.initial_ppc[covered].sum()) if method == "hybrid" else 0.0
    h, U = 1e-3, scene.potential
    k = float((U(np.array(0.5 + h)) - 2 * U(np.array(0.5)) + U(np.array(0.5 - h))) / h**2)
    shares = theory.trap_walk_shares(cells, 1.0, scene.dt, k, 0.5)
    return scene, covered, float(scene.initial_ppc.sum()) - lam, lam, shares


def tail_scores(mean, var, members, n, lam, shares, cells) -> list[dict]:
    """Per cell of ``cells``: the ensemble's count mean and variance against the exact
    Bin(n, p) + Poisson(lam p) of :func:`theory.fixed_and_poisson_moments` (p = ``shares[i]``).
    Where the ensemble's expected total ``members · E[count]`` is at least 100 (its skewness at
    most 0.1) as z-scores, SE(mean) = √(κ₂/M) and SE(s²) = √((μ₄ − κ₂²)/M); below, the normal
    z means nothing, and the test is exact: the total over the members is Poisson (to relative
    O(p)), ``p_value`` its two-sided tail probability. There the variance is not scored: all but
    about ``M (E count)²/2 < 0.01`` members hold 0 or 1, so s² = mean (1 − mean) + O(1/M) repeats it."""
    from ti_dk.core import theory

    rows = []
    for i in cells:
        b = theory.fixed_and_poisson_moments(n, lam, float(shares[i]))
        row = {"cell": int(i), "exact_mean": float(b["mean"]), "exact_variance": float(b["variance"]),
               "z_mean": None, "z_var": None, "p_value": None}
        if members * b["mean"] >= 100:
            row["z_mean"] = (mean[i] - b["mean"]) / math.sqrt(b["variance"] / members)
            row["z_var"] = (var[i] - b["variance"]) / math.sqrt((b["kurtosis"] - 1) * b["variance"] ** 2 / members)
        else:
            row["p_value"] = poisson_two_sided(members * b["mean"], round(mean[i] * members))
        rows.append(row)
    return rows


def poisson_two_sided(mu: float, k: int) -> float:
    """2 min(P(X ≤ k), P(X ≥ k)) for X ~ Poisson(mu), capped at 1."""
    pmf = [math.exp(-mu)]
    for j in range(1, k + 1):
        pmf.append(pmf[-1] * mu / j)
    below = sum(pmf)
    return min(1.0, 2 * min(below, 1.0 - below + pmf[-1]))


def run_steps(s, steps, check=None):
    """Step ``s``; return every diagnostic per step, index 0 being the state after the start."""
    rows = [s.diagnostics()]
    for n in range(steps):
        s.step(n)
        rows.append(s.diagnostics())
        if check:
            check(s)
    return {k: np.array([r[k] for r in rows]) for k in rows[0]}


def covered_nonnegative(s):
    """A hybrid solver's covered cells: non-negative, whole particles, and as many as its pool holds."""
    q, region = s.density(), s.region()
    assert np.all(q[region] >= 0)
    # covered cells hold whole particles, and they are the particles in the pool
    counts = q[region] * s.grid.cell_volume
    assert np.allclose(counts, np.round(counts), atol=1e-9)
    assert round(counts.sum()) == s.diagnostics()["particles"]


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


def fv_mean_step(q, dx, dt, boundary, reservoir, ubar=None):
    """One step of the deterministic FV scheme in NumPy, face by face: F = ½ Δq/Δx across each face
    (eq. 10), or with ``ubar`` (Ū on the grid padded by one cell) the drift's Scharfetter–Gummel
    form F = ½ (B(−δ) q_R − B(δ) q_L)/Δx, δ = Ū_R − Ū_L, B(z) = z/(e^z − 1); the reservoir value
    beyond a Dirichlet side, the opposite cell across a periodic one, no flux through Neumann."""
    out = q.copy()
    for a, (h, (lo, hi), (r_lo, r_hi)) in enumerate(zip(dx, boundary, reservoir)):
        qm = np.moveaxis(q, a, 0)
        n = qm.shape[0]
        left = np.concatenate([qm[-1:] if lo == "periodic" else np.full((1, *qm.shape[1:]), r_lo), qm])
        right = np.concatenate([qm, qm[:1] if hi == "periodic" else np.full((1, *qm.shape[1:]), r_hi)])
        if ubar is None:
            F = 0.5 / h * (right - left)  # faces 0 … n
        else:
            um = np.moveaxis(ubar[tuple(slice(None) if b == a else slice(1, -1) for b in range(q.ndim))], a, 0)
            ul = np.concatenate([um[-2:-1] if lo == "periodic" else um[:1], um[1:-1]])
            ur = np.concatenate([um[1:-1], um[1:2] if lo == "periodic" else um[-1:]])
            d = ur - ul
            with np.errstate(invalid="ignore", divide="ignore"):
                b = np.where(d == 0, 1.0, d / np.where(d == 0, 1.0, np.expm1(d)))  # B(δ); B(−δ) = B(δ) + δ
            F = 0.5 / h * ((b + d) * right - b * left)
        if lo == "neumann":
            F[0] = 0.0
        if hi == "neumann":
            F[n] = 0.0
        out += np.moveaxis(dt * (F[1:] - F[:-1]) / h, 0, a)
    return out


def file_tree(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones included) with the SHA-256 of its bytes."""
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def no_hang(seconds: int = 30):
    """A context in which a call that blocks (a read from a FIFO) fails after ``seconds`` with
    ``TimeoutError`` (SIGALRM), rather than hanging the test run."""
    import contextlib
    import signal

    def expire(signum, frame):
        raise TimeoutError(f"still waiting after {seconds} s")

    @contextlib.contextmanager
    def guard():
        old = signal.signal(signal.SIGALRM, expire)
        signal.alarm(seconds)
        try:
            yield
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, old)

    return guard()
