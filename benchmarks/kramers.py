"""Issue 28: the crossing rate of the double well (scenes/doublewell2d.toml) in `particle`, `fv` and
`hybrid`: the particles in the right well (x > ½) against time, the fitted rate per method, and a
Kramers estimate beside them.

    PYTHONPATH=. python benchmarks/kramers.py [--cells 32] [--members 6] [--t-end 0.05] [--threads 1]
        [--methods particle,hybrid,fv] [--set threshold=50]

Each member runs on its own (``ensemble = 1``, ``member0 = k``: the same streams as member k of one
ensemble run) so that its right-well count N_R(t) is known and the spread over members gives the
standard errors; the wall time of a method is the sum of its members' runs (compiling included).
The start keeps the scene's density per unit volume (4e6 e^{-V} on the blob) when ``--cells``
changes. Rates: the slope of f = N_R/N against t on t >= ``--fit-from`` (least squares per member,
mean and standard error over members) and the symmetric two-state model's k from
-ln(1 - 2f)/2 against t, which is the same slope while f << ½.
"""
import argparse
import json
import math
import time

import numpy as np

import ti_dk
from ti_dk.output.series import two_state_rate

GAMMA, D = 5e-4, 0.5  # the scene's V = [(x−0.3)²(x−0.7)² + (y−½)⁴]/γ, U = 2V; D = ½ in the code's units
BLOB = "exp(-((x-0.3)**2*(x-0.7)**2 + (y-0.5)**4)/5e-4)*step(x-0.2)*step(0.4-x)*step(y-0.25)*step(0.75-y)"


def u_x(x: np.ndarray) -> np.ndarray:
    """U along the line y = ½ (in kT)."""
    return 2 * (x - 0.3) ** 2 * (x - 0.7) ** 2 / GAMMA


def kramers_rate() -> tuple[float, float, float, float]:
    """One-way Kramers rate (D/2π) sqrt(U''(min) |U''(saddle)|) e^{-ΔU} with U'' by central
    differences; the y part of U is the same at the minimum and the saddle, so its partition
    functions cancel. Returns (rate, U''(min), U''(saddle), ΔU)."""
    h = 1e-4
    d2 = lambda x: (u_x(x + h) - 2 * u_x(x) + u_x(x - h)) / h**2  # noqa: E731
    umin, usad = float(d2(0.3)), float(d2(0.5))
    du = float(u_x(0.5) - u_x(0.3))
    return D / (2 * math.pi) * math.sqrt(umin * abs(usad)) * math.exp(-du), umin, usad, du


def member_series(method: str, cells: int, members: int, t_end: float, rows: int, c: float, extra: dict):
    """N_R(t) and N(t) of each member, (members, rows + 1) with t = 0 first, the times, and the
    wall seconds of all the method's runs."""
    times = [t_end * (k + 1) / rows for k in range(rows - 1)]
    scene = ti_dk.load_scene("doublewell2d", method=method, compare=None, cells=[cells, cells], t_end=t_end,
                             output_times=times, ensemble=1, C=c,
                             density=f"{4e6 / cells**2!r}*{BLOB}", **extra)
    x = (np.arange(cells) + 0.5) / cells
    right, total, wall = [], [], 0.0
    for m in range(members):
        t0 = time.perf_counter()
        res = ti_dk.run(scene, progress=False, member0=m)
        wall += time.perf_counter() - t0
        n_x = res.stats.mean.sum(axis=2) * res.cell_volume  # (rows, cells in x): particles per column
        n0 = scene.initial_ppc.sum()
        right.append(np.concatenate([[scene.initial_ppc[x > 0.5].sum()], n_x[:, x > 0.5].sum(axis=1)]))
        total.append(np.concatenate([[n0], n_x.sum(axis=1)]))
    return np.array(right), np.array(total), np.concatenate([[0.0], res.times]), wall


def json_pair(text: str) -> tuple[str, object]:
    """KEY=VALUE with VALUE read as JSON (a bare word stays text)."""
    key, value = text.split("=", 1)
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def slopes(t: np.ndarray, y: np.ndarray, t_from: float) -> np.ndarray:
    """Least-squares slope of each row of y against t over t >= t_from."""
    keep = t >= t_from - 1e-12
    return np.polyfit(t[keep], y[:, keep].T, 1)[0]


def mean_se(v: np.ndarray) -> tuple[float, float]:
    return float(v.mean()), float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=32)
    ap.add_argument("--members", type=int, default=6)
    ap.add_argument("--t-end", type=float, default=0.05)
    ap.add_argument("--rows", type=int, default=10, help="output rows (equally spaced, t_end the last)")
    ap.add_argument("--fit-from", type=float, default=0.01, help="fit the rate on t >= this (after the blob relaxes)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--C", type=float, default=0.02, help="time step (the scene's 0.025 is past fv's limit at 32x32)")
    ap.add_argument("--methods", default="particle,hybrid,fv")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a further scene override (VALUE as JSON), e.g. --set threshold=50")
    args = ap.parse_args()
    ti_dk.init("cpu", args.threads)
    methods = args.methods.split(",")
    out = {m: member_series(m, args.cells, args.members, args.t_end, args.rows, args.C,
                            dict(json_pair(kv) for kv in args.set)) for m in methods}
    t = next(iter(out.values()))[2]
    n0 = next(iter(out.values()))[1][0, 0]
    sets = "".join(", " + kv for kv in args.set)
    print(f"doublewell2d, {args.cells}x{args.cells} cells, {args.members} members per method, t_end = {args.t_end}, "
          f"C = {args.C}, {args.threads} thread(s){sets}; N(0) = {n0:.0f} particles per member\n")
    print("| t | " + " | ".join(f"N_R {m}" for m in methods) + " |")
    print("| ---: | " + " | ".join("---:" for _ in methods) + " |")
    for k, tk in enumerate(t):
        cells = [f"{mean_se(out[m][0][:, k])[0]:.1f} ± {mean_se(out[m][0][:, k])[1]:.1f}" for m in methods]
        print(f"| {tk:.4f} | " + " | ".join(cells) + " |")
    rate, umin, usad, du = kramers_rate()
    print(f"\nKramers (one way): U''(min) = {umin:.1f}, U''(saddle) = {usad:.1f}, dU = {du:.3f} -> k = {rate:.4f}\n")
    print(f"| method | slope of N_R/N, t >= {args.fit_from} | two-state k | k / Kramers | wall [s] | s per member |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    rates = {}
    for m in methods:
        right, total, _, wall = out[m]
        f = right / total
        s = mean_se(slopes(t, f, args.fit_from))
        k2 = mean_se(two_state_rate(t, f, args.fit_from))
        rates[m] = k2
        print(f"| {m} | {s[0]:.4f} ± {s[1]:.4f} | {k2[0]:.4f} ± {k2[1]:.4f} | {k2[0] / rate:.2f} | {wall:.1f} | "
              f"{wall / args.members:.1f} |")
    if "particle" in rates:
        for m in methods:
            if m != "particle":
                z = (rates[m][0] - rates["particle"][0]) / math.hypot(rates[m][1], rates["particle"][1])
                print(f"{m} vs particle: z = {z:+.2f} ({'within' if abs(z) < 2 else 'beyond'} 2 standard errors)")


if __name__ == "__main__":
    main()
