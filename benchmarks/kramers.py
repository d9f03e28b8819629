"""Issue 28: the crossing rate of the double well (scenes/doublewell2d.toml) in `particle`, `fv` and
`hybrid`: the particles in the right well (x > ½) against time, the rate per method from
``ti_dk.crossing_rate``, and a Kramers estimate beside them.

    PYTHONPATH=. python benchmarks/kramers.py [--cells 32] [--members 6] [--t-end 0.05] [--threads 1]
        [--methods particle,hybrid,fv] [--set threshold=50]

One ensemble run per method with all the members; the scene's observables ``left`` (x < ½) and
``right`` (x > ½) are recorded per member every ``sample_every`` steps, so the spread over the
members gives the standard errors; the wall time of a method is its run's (compiling included).
The start keeps the scene's density per unit volume (4e6 e^{-V} on the blob) when ``--cells``
changes. Rates on t >= ``--fit-from``: ``ti_dk.crossing_rate`` (the symmetric two-state model's k,
the slope of -ln(1 - 2f)/2 with f = N_R/(N_L + N_R), mean and standard error over the members)
and, beside it, the plain least-squares slope of f, which is the same while f << ½.
"""
import argparse
import json
import math
import time

import numpy as np

import ti_dk
from ti_dk.output.series import mean_se

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


def ensemble_run(method: str, cells: int, members: int, t_end: float, c: float, extra: dict):
    """One ensemble run of the scene with all the members (its observables recorded), the scene
    and the run's wall seconds."""
    scene = ti_dk.load_scene("doublewell2d", method=method, compare=None, cells=[cells, cells], t_end=t_end,
                             output_times=[], ensemble=members, C=c,
                             density=f"{4e6 / cells**2!r}*{BLOB}", **extra)
    t0 = time.perf_counter()
    res = ti_dk.run(scene, progress=False)
    return res, scene, time.perf_counter() - t0


def json_pair(text: str) -> tuple[str, object]:
    """KEY=VALUE with VALUE read as JSON (a bare word stays text)."""
    key, value = text.split("=", 1)
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def slopes(t: np.ndarray, f: np.ndarray, t_from: float) -> np.ndarray:
    """Least-squares slope of f against t over t >= t_from, per member (f: (records, members))."""
    keep = t >= t_from - 1e-12
    return np.polyfit(t[keep], f[keep], 1)[0]


def pm(mean_and_se, digits: int) -> str:
    return f"{float(mean_and_se[0]):.{digits}f} ± {float(mean_and_se[1]):.{digits}f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=32)
    ap.add_argument("--members", type=int, default=6)
    ap.add_argument("--t-end", type=float, default=0.05)
    ap.add_argument("--rows", type=int, default=10, help="rows of the N_R table (equally spaced, t_end the last)")
    ap.add_argument("--fit-from", type=float, default=0.01, help="fit the rate on t >= this (after the blob relaxes)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--C", type=float, default=0.02, help="time step (the scene's 0.025 is past fv's limit at 32x32)")
    ap.add_argument("--methods", default="particle,hybrid,fv")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a further scene override (VALUE as JSON), e.g. --set threshold=50")
    args = ap.parse_args()
    ti_dk.init("cpu", args.threads)
    methods = args.methods.split(",")
    extra = dict(json_pair(kv) for kv in args.set)
    out = {m: ensemble_run(m, args.cells, args.members, args.t_end, args.C, extra) for m in methods}
    res, scene, _ = next(iter(out.values()))
    t = res.series["time"]
    rows = [int(np.argmin(abs(t - args.t_end * (k + 1) / args.rows))) for k in range(args.rows)]
    sets = "".join(", " + kv for kv in args.set)
    print(f"doublewell2d, {args.cells}x{args.cells} cells, {args.members} members per method (one ensemble run "
          f"each), t_end = {args.t_end}, C = {args.C}, {args.threads} thread(s){sets}; "
          f"N(0) = {scene.initial_ppc.sum():.0f} particles per member, {len(t)} records\n")
    print("| t | " + " | ".join(f"N_R {m}" for m in methods) + " |")
    print("| ---: | " + " | ".join("---:" for _ in methods) + " |")
    for k in rows:
        print(f"| {t[k]:.4f} | " + " | ".join(pm(mean_se(out[m][0].series["right"][k]), 1) for m in methods) + " |")
    rate, umin, usad, du = kramers_rate()
    print(f"\nKramers (one way): U''(min) = {umin:.1f}, U''(saddle) = {usad:.1f}, dU = {du:.3f} -> k = {rate:.4f}\n")
    print(f"| method | slope of N_R/N, t >= {args.fit_from} | two-state k | k / Kramers | wall [s] | s per member |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    rates = {}
    for m in methods:
        res, _, wall = out[m]
        right, left = res.series["right"], res.series["left"]
        s = mean_se(slopes(res.series["time"], right / (left + right), args.fit_from))
        k2 = rates[m] = ti_dk.crossing_rate(res, "left", "right", t_from=args.fit_from)
        print(f"| {m} | {pm(s, 4)} | {pm((k2.value, k2.se), 4)} | {k2.value / rate:.2f} | {wall:.1f} | "
              f"{wall / args.members:.1f} |")
    if "particle" in rates:
        p = rates["particle"]
        for m in methods:
            if m != "particle":
                z = (rates[m].value - p.value) / math.hypot(rates[m].se, p.se)
                print(f"{m} vs particle: z = {z:+.2f} ({'within' if abs(z) < 2 else 'beyond'} 2 standard errors)")


if __name__ == "__main__":
    main()
