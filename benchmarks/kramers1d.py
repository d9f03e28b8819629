"""Issue 28 in 1D: the x part of the double well (scenes/doublewell2d.toml), where the particle
method's mean is known exactly, against the hybrid's members.

    PYTHONPATH=. python benchmarks/kramers1d.py [--cells 32] [--C 0.02] [--members 100] [--N 15000]
        [--set threshold=50] [--alt 15,16 --every 10] [--tag-mean 10]

U(x) = 2 (x − 0.3)² (x − 0.7)² / 5e-4 and the start (the scene's e^{−V} blob on [0.2, 0.4), cell
centres, N particles a member) are the x parts of the 2D scene; both are separable and the clamped
walk moves each axis on its own, so the x-marginal of the 2D particle method is this 1D walk and
its crossing fraction f(t) = N_R/N is the 2D one. Exact answers, no sampling:

- ``walk``: the mean of the particle method, the density on 256 bins a cell moved by the exact
  Gaussian step (drift −½U'Δt at the bin centre; the clamp at ±Δx, p ≈ 1e-12 here, left out);
- ``fv``: the mean of fv, the deterministic Scharfetter–Gummel scheme (q̄ of eq. 10).

Then ``--members`` hybrid members (one ensemble, one thread) give f(t) ± its standard error and
the rate k, the slope of −ln(1 − 2f)/2 on t ≥ 0.01, per member. ``--set`` changes a scene key;
``--alt a,b`` with ``--set regrid_interval=0`` moves the region's edge between cells a and b every
``--every`` steps (the same for every member: a region that does not depend on the state);
``--tag-mean K`` tags every K steps from q̄ instead of each member's own q (likewise).
"""
import argparse
import json
import math
import time

import numpy as np

import ti_dk
from ti_dk.core import theory
from ti_dk.output.series import two_state_rate
from ti_dk.control.registry import make_solver

FORMULA = "2*(x-0.3)**2*(x-0.7)**2/5e-4"
BLOB = "exp(-((x-0.3)**2*(x-0.7)**2)/5e-4)*step(x-0.2)*step(0.4-x)"


def u_prime(x):
    return 2 * (2 * (x - 0.3) * (x - 0.7) ** 2 + 2 * (x - 0.3) ** 2 * (x - 0.7)) / 5e-4


def blob(cells: int) -> np.ndarray:
    """The start's formula (BLOB) at the cell centres."""
    x = (np.arange(cells) + 0.5) / cells
    return np.exp(-(x - 0.3) ** 2 * (x - 0.7) ** 2 / 5e-4) * ((x >= 0.2) & (x < 0.4))


def start(cells: int) -> np.ndarray:
    """The blob's share of each cell."""
    return blob(cells) / blob(cells).sum()


def fit_rate(t: np.ndarray, f: np.ndarray, t_from: float = 0.01) -> np.ndarray:
    """Slope of −ln(1 − 2f)/2 against t on t ≥ t_from (last axis of f: time)."""
    return two_state_rate(t, f, t_from)


def walk_mean(cells: int, dt: float, times: np.ndarray, sub: int = 256) -> np.ndarray:
    """f(t) of the particle method: the fine-bin transition matrix of the Euler–Maruyama step
    (:func:`ti_dk.core.theory.walk_crossing_fraction`)."""
    return theory.walk_crossing_fraction(u_prime, start(cells), dt, times, sub=sub)


def fv_mean(cells: int, dt: float, times: np.ndarray) -> np.ndarray:
    """f(t) of fv's mean: the Scharfetter–Gummel scheme, Dirichlet walls at density 0."""
    from ti_dk.methods.fluxes import bernoulli
    from ti_dk.core.expr import Potential

    h = 1.0 / cells
    ub = Potential.of(FORMULA, 1).cell_values((cells,), (1.0,), pad=1)
    d = np.diff(ub)
    cl, cr = bernoulli(d), bernoulli(d) + d

    def step(q):
        qq = np.concatenate([[0.0], q, [0.0]])
        F = 0.5 / h * (cr * qq[1:] - cl * qq[:-1])
        return q + dt / h * (F[1:] - F[:-1])
    return _sample(step, start(cells), (np.arange(cells) + 0.5) * h > 0.5, dt, times)


def _sample(step, p, right, dt, times):
    out, n = [], 0
    for t in times:
        while n < round(t / dt):
            p, n = step(p), n + 1
        out.append(p[right].sum() / p.sum())
    return np.array(out)


def hybrid_members(args, times: np.ndarray):
    """f(t) of each member, (members, times), and the seconds taken."""
    n = args.cells
    extra = dict(json_pair(kv) for kv in args.set)
    scale = float(args.N / blob(n).sum())
    scene = ti_dk.load_scene("doublewell2d", method="hybrid", compare=None, cells=[n], C=args.C, t_end=times[-1],
                             potential=FORMULA, density=f"{scale!r}*{BLOB}", ensemble=args.members, seed=11, **extra)
    s = make_solver(scene, scene.initial_ppc)
    right = (np.arange(n) + 0.5) / n > 0.5
    alt = [int(v) for v in args.alt.split(",")] if args.alt else []
    f, k, t0 = np.zeros((args.members, times.size)), 1, time.perf_counter()  # f(0) = 0: the blob is left
    for step in range(round(times[-1] / scene.dt)):
        if alt and step and step % args.every == 0:
            m = np.zeros((args.members, n), dtype=bool)
            m[:, alt[(step // args.every) % len(alt)]:] = m[:, :8] = True
            s.set_region(m, step)
        if args.tag_mean and step and step % args.tag_mean == 0:
            s.set_region(s.regions.plan(np.broadcast_to(s.spde.qbar.to_numpy() / n, (args.members, n)).copy())[0],
                         step)
        s.step(step)
        while k < times.size and step + 1 == round(times[k] / scene.dt):
            q = s.density()
            f[:, k] = q[:, right].sum(1) / q.sum(1)
            k += 1
    return f, scene.dt, time.perf_counter() - t0


def json_pair(text: str):
    key, value = text.split("=", 1)
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=32)
    ap.add_argument("--C", type=float, default=0.02)
    ap.add_argument("--N", type=float, default=15000, help="particles a member")
    ap.add_argument("--members", type=int, default=100)
    ap.add_argument("--t-end", type=float, default=0.05)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--alt", default="")
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--tag-mean", type=int, default=0)
    args = ap.parse_args()
    ti_dk.init("cpu", 1)
    times = args.t_end * np.arange(0, 11) / 10
    f, dt, wall = hybrid_members(args, times)
    walk, fv = walk_mean(args.cells, dt, times), fv_mean(args.cells, dt, times)
    kw, kf, kh = fit_rate(times, walk), fit_rate(times, fv), fit_rate(times, f)
    se_f = f[:, -1].std(ddof=1) / math.sqrt(args.members)
    se_k = kh.std(ddof=1) / math.sqrt(args.members)
    print(f"{args.cells} cells, C = {args.C}, {args.members} members, {' '.join(args.set)} "
          f"{'alt ' + args.alt + '/' + str(args.every) if args.alt else ''}"
          f"{'tag on q-bar every ' + str(args.tag_mean) if args.tag_mean else ''} ({wall:.0f} s)")
    print(f"f(t_end): walk {walk[-1]:.6f}, fv {fv[-1]:.6f}, hybrid {f[:, -1].mean():.6f} ± {se_f:.6f} "
          f"(/walk {f[:, -1].mean() / walk[-1]:.3f}, z = {(f[:, -1].mean() - walk[-1]) / se_f:+.1f})")
    print(f"k: walk {kw:.4f}, fv {kf:.4f}, hybrid {kh.mean():.4f} ± {se_k:.4f} "
          f"(/walk {kh.mean() / kw:.3f}, z = {(kh.mean() - kw) / se_k:+.1f})")


if __name__ == "__main__":
    main()
