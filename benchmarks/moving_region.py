"""The hybrid with its region moving, against the exact answer at >= 10⁵ members (issue 40's trap).

    PYTHONPATH=. python benchmarks/moving_region.py [--members 100000] [--chunk 25000]
        [--cases particle fixed boxes tiles] [--threads 2]

A harmonic trap, U = ½((x − ½)/σ)², σ = 0.08, on 100 Neumann cells of [0, 1], N = 300 particles
(3 per cell on average), started at the cell-averaged Boltzmann profile (``init = "boltzmann"``),
C = 1/16, ``threshold`` 5, t_end = 0.005 (800 steps). The cases:

- ``particle``: the particle method (``particle_init = "exact"``: exactly 300 particles);
- ``fixed``: the hybrid with its first region kept (``regrid_interval = 0``);
- ``boxes``: the hybrid regridded every 10 steps with extensions on demand (the defaults) and the
  paper's Berger–Rigoutsos boxes (``region = "boxes"``);
- ``tiles``: the same with the region of tiles (the default; in 1D tiles of one cell) and its
  hysteresis (``release`` 1.5).

Exact answer: every cell's expected count is N p_i. The hybrid's mean total is N (its start, its
sampling of particles from the SPDE, integer part plus a Bernoulli, and its synchronisation are
unbiased), and p_i is the stationary law of the clamped Euler–Maruyama walk the particles run
(:func:`ti_dk.core.theory.trap_walk_shares`; started at the Boltzmann profile, which differs from it
by less than 0.2 SE per cell at 10⁵ members, both are printed). Each cell's mean is scored as
z = (mean − N p_i)/SE with SE from the members' own variance (members are independent), over the
cells whose expected count over all members is at least 1,000 (normal enough). An exact hybrid, like
the particle method, gives z ~ N(0, 1): rms z near 1 and no pattern across the region's edges.
"""
import argparse
import math
import time

import numpy as np

import ti_dk
from ti_dk.core.stats import CellStats
from ti_dk.core.theory import trap_walk_shares

SIGMA, CELLS, N = 0.08, 100, 300
CASES = {
    "particle": dict(method="particle", particle_init="exact"),
    "fixed": dict(method="hybrid", regrid_interval=0),
    "boxes": dict(method="hybrid", region="boxes"),
    "tiles": dict(method="hybrid", region="tiles"),
}


def trap_scene(case: str, members: int):
    """The trap of the module docstring, run as ``case``."""
    scene = ti_dk.load_scene("trap1d").replace(
        cells=[CELLS], potential=f"0.5*((x-0.5)/{SIGMA})**2", ppc=N / CELLS, C=0.0625, t_end=0.005,
        output_times=[], ensemble=members, threshold=5.0, t_equil=None)
    return scene.replace(**CASES[case])


def moments(scene, members: int, chunk: int):
    """Per-cell mean and variance of the count at t_end (one sample per member) over ``members`` members, ``chunk`` at a time
    (``member0``: the same streams as one ensemble), and the wall seconds."""
    merged, wall = CellStats(scene.grid.cells, scene.grid.cell_volume), 0.0
    for start in range(0, members, chunk):
        size = min(chunk, members - start)
        t0 = time.perf_counter()
        res = ti_dk.run(scene.replace(ensemble=size), progress=False, member0=start)
        wall += time.perf_counter() - t0
        merged.merge_row(res.rows[-1])
        print(f"  members {start}..{start + size - 1}: {time.perf_counter() - t0:.1f} s", flush=True)
    row, vol = merged.row(), scene.grid.cell_volume
    return row["mean"] * vol, row["variance"] * vol**2, wall


def scores(mean, var, members: int, shares) -> np.ndarray:
    """z of each cell's mean against ``N · shares`` (NaN where the expected count over all members is
    below 1,000)."""
    exact = N * shares
    z = (mean - exact) / np.sqrt(np.maximum(var, 1e-300) / members)
    return np.where(exact * members >= 1000, z, np.nan)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=100_000)
    ap.add_argument("--chunk", type=int, default=25_000)
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--save", help="an .npz file for the per-cell means and variances")
    args = ap.parse_args()
    ti_dk.init("cpu", args.threads)
    M, out = args.members, {}
    for case in args.cases:
        scene = trap_scene(case, M)
        dt = scene.dt
        walk = trap_walk_shares(CELLS, 1.0, dt, 1.0 / SIGMA**2, 0.5)
        boltz = scene.grid.potential.boltzmann_weights((CELLS,), (1.0,))
        print(f"{case}: {scene.n_steps} steps of {dt:.3g}, {M} members in chunks of {args.chunk}", flush=True)
        mean, var, wall = moments(scene, M, args.chunk)
        out[case] = dict(mean=mean, var=var)
        zw, zb = scores(mean, var, M, walk), scores(mean, var, M, boltz)
        ok = ~np.isnan(zw)
        worst = int(np.nanargmax(np.abs(zw)))
        print(f"| {case} | {M} | {wall:.0f} s | total {mean.sum():.4f} (exact {N}) | walk: max |z| "
              f"{np.nanmax(np.abs(zw)):.2f} (cell {worst}), rms {math.sqrt(np.nanmean(zw**2)):.2f}, mean "
              f"{np.nanmean(zw):+.2f} | Boltzmann: max |z| {np.nanmax(np.abs(zb)):.2f}, rms "
              f"{math.sqrt(np.nanmean(zb**2)):.2f} | {int(ok.sum())} cells |", flush=True)
        print("  z by cell (walk):", " ".join(f"{i}:{z:+.1f}" for i, z in enumerate(zw) if not np.isnan(z)))
    if args.save:
        np.savez(args.save, **{f"{c}_{k}": v for c, d in out.items() for k, v in d.items()})


if __name__ == "__main__":
    main()
