"""The hybrid with its region moving, against the exact answer at >= 10⁵ members (issue 40's trap).

    PYTHONPATH=. python benchmarks/moving_region.py [--members 100000] [--chunk 25000]
        [--cases particle fixed tiles tiles_member ...] [--threads 2]

A harmonic trap, U = ½((x − ½)/σ)², σ = 0.08, on 100 Neumann cells of [0, 1], N = 300 particles
(3 per cell on average), started at the cell-averaged Boltzmann profile (``init = "boltzmann"``),
C = 1/16, ``threshold`` 5, t_end = 0.005 (800 steps). The cases:

- ``particle``: the particle method (``particle_init = "exact"``: exactly 300 particles);
- ``fixed``: the hybrid with its first region kept (``regrid_interval = 0``);
- ``tiles``: the hybrid regridded every 10 steps with the defaults: tiles (in 1D tiles of one
  cell) with hysteresis (``release`` 1.5), tagged from the deterministic q̄ (``region_from =
  "mean"``, one region for every member), no extensions (``regrid_floor = 0``);
- ``tiles_guard``: the same with extensions on demand (``regrid_floor = 0.6``: a member's
  cell below 3 particles is covered before the next step, chosen by the member's own density);
- ``tiles_member``: tiles tagged from each member's own density with extensions
  (``region_from = "member"``, ``regrid_floor = 1``: the defaults before this benchmark);
- ``boxes``: Berger–Rigoutsos boxes (``region = "boxes"``) from q̄; ``boxes_member``: the paper's,
  from each member's own density with extensions.

The void cases (``void_fixed``, ``void_tiles``, ``void_member``, ``void_boxes``): the authors' void of the interface
tests, the region fixed or regridded every 3 steps, against the clamped walk's own exact mean
(:func:`ti_dk.core.theory.particle_counts_periodic`); ``void2d_tiles`` and ``void2d_member``: the 2D
void of the tests (20 × 20 periodic cells, 6 per cell, an empty slab 0.4 ≤ x ≤ 0.6, C = 1/16,
80 steps) at threshold 5, its region regridded every 3 steps as the slab fills (from q̄ with the
default tiles of 2, or from each member's own density), against the product of clamped walks.
``cross2d_tiles`` and ``cross2d_fixed``: the 2D void's slab and the same slab along y, a void
shaped as a cross (6 per cell elsewhere): its region has concave corners where the arms meet, whose
ghost cells have covered neighbours beyond two faces, in flat SPDE surroundings; regridded every
3 steps from q̄ (tiles of 2), or fixed. ``blob2d_fixed`` and ``blob2d_tiles``: a dense blob in a thin gas on the same grid (``BLOB``: 1 per
cell far from it, 12 at its centre), threshold 5: the region covers all but the blob's core, an
island of SPDE cells whose ghost cells sit in the region's concave corners (covered neighbours
beyond two faces), with tiles of one cell: fixed, or regridded every 3 steps from q̄ as the blob
spreads and the island shrinks.

Exact answer (trap): every cell's expected count is N p_i. The hybrid's mean total is N (its start, its
sampling of particles from the SPDE, integer part plus a Bernoulli, and its synchronisation are
unbiased), and p_i is the stationary law of the clamped Euler–Maruyama walk the particles run
(:func:`ti_dk.core.theory.trap_walk_shares`; the start, the cell-averaged Boltzmann profile, differs
from it by less than 0.2 SE per cell at 10⁵ members). Each cell's mean is scored as
z = (mean − N p_i)/SE with SE from the members' own variance (members are independent), over the
cells whose expected count over all members is at least 1,000 (normal enough). An exact hybrid, like
the particle method, gives z ~ N(0, 1): rms z near 1 and no pattern across the region's edges.
"""
import argparse
import math
import warnings

import numpy as np

import ti_dk
from ti_dk.core import theory
from ti_dk.core.theory import trap_walk_shares
from ti_dk.scene.load import command_overrides
from ti_dk.scene.schema import ClampWarning
from trap_tails import chunked_moments  # a sibling script: each chunk a run with member0

SIGMA, CELLS, N = 0.08, 100, 300
MEMBER = dict(region_from="member", regrid_floor=1.0)  # the region from each member's own density
CASES = {
    "particle": dict(method="particle", particle_init="exact"),
    "fixed": dict(method="hybrid", regrid_interval=0),
    "tiles": dict(method="hybrid"),
    "tiles_guard": dict(method="hybrid", regrid_floor=0.6),
    "tiles_member": dict(method="hybrid", **MEMBER),
    "boxes": dict(method="hybrid", region="boxes"),
    "boxes_member": dict(method="hybrid", region="boxes", **MEMBER),
    "void_fixed": dict(regrid_interval=0),
    "void_tiles": dict(regrid_interval=3),
    "void_member": dict(regrid_interval=3, **MEMBER),
    "void_boxes": dict(regrid_interval=3, region="boxes"),
    "void2d_tiles": dict(regrid_interval=3),
    "void2d_member": dict(regrid_interval=3, **MEMBER),
    "cross2d_tiles": dict(regrid_interval=3),
    "cross2d_fixed": dict(regrid_interval=0),
    "blob2d_fixed": dict(regrid_interval=0, tile=1),
    "blob2d_tiles": dict(regrid_interval=3, tile=1),
}
BLOB = "1 + 12*exp(-((x-0.5)**2 + (y-0.5)**2) / (2*0.1**2))"  # blob2d: particles per cell
CROSS = "6*(1 - step(x-0.4)*step(0.6-x))*(1 - step(y-0.4)*step(0.6-y))"  # cross2d: particles per cell


def trap_scene(case: str, members: int):
    """The trap of the module docstring, run as ``case``; or (``void_*``) the authors' void of
    ``tests/hybrid/test_solver.py`` (100 periodic cells, 12.5 per cell, cells 40–59 empty, C = 1/8,
    200 steps), with its region fixed or regridded every 3 steps."""
    if case.startswith(("blob2d", "cross2d")):  # concave corners: an SPDE island, a cross-shaped void
        return ti_dk.load_scene("void1d", method="hybrid", init="expression", cells=[20, 20], C=0.0625,
                                density=BLOB if case.startswith("blob") else CROSS, t_end=0.0125, threshold=5,
                                seed=2, output_times=[], ensemble=members, **CASES[case])
    if case.startswith("void2d"):  # the 2D void of the tests, its region moving (threshold 5 at 6 per cell)
        return ti_dk.load_scene("void1d", method="hybrid", cells=[20, 20], ppc=6, void_lo=0.4, void_hi=0.6,
                                C=0.0625, t_end=0.0125, threshold=5, seed=2, output_times=[], ensemble=members,
                                **CASES[case])
    if case.startswith("void"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ClampWarning)  # C = 1/8 clamps 0.5 % of the steps: in the exact answer
            return ti_dk.load_scene("void1d", method="hybrid", ppc=12.5, void_lo=0.4, void_hi=0.6, C=0.125,
                                    t_end=0.0025, seed=11, output_times=[], ensemble=members, **CASES[case])
    scene = ti_dk.load_scene("trap1d").replace(
        cells=[CELLS], potential=f"0.5*((x-0.5)/{SIGMA})**2", ppc=N / CELLS, C=0.0625, t_end=0.005,
        output_times=[], ensemble=members, threshold=5.0, t_equil=None)
    return scene.replace(**CASES[case])


def exact_mean(case: str, scene) -> np.ndarray:
    """Each cell's exact expected count at t_end: N times the clamped walk's stationary shares (the
    trap), or the clamped walk's own transition from the start (the void)."""
    if case.startswith(("void", "blob", "cross")):
        lengths = (1.0,) * len(scene.grid.cells)
        return theory.particle_counts_periodic(scene.initial_ppc, lengths, scene.dt, scene.n_steps)["mean"]
    return N * trap_walk_shares(CELLS, 1.0, scene.dt, 1.0 / SIGMA**2, 0.5)


def scores(mean, var, members: int, exact) -> np.ndarray:
    """z of each cell's mean against ``exact`` (NaN where the expected count over all members is
    below 1,000)."""
    z = (mean - exact) / np.sqrt(np.maximum(var, 1e-300) / members)
    return np.where(exact * members >= 1000, z, np.nan)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=100_000)
    ap.add_argument("--chunk", type=int, default=25_000)
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--save", help="an .npz file for the per-cell means and variances")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change a key of every case (a number or a word), e.g. --set regrid_floor=0")
    args = ap.parse_args()
    extra = command_overrides(args.set, {})
    ti_dk.init("cpu", args.threads)
    M, out = args.members, {}
    for case in args.cases:
        scene = trap_scene(case, M).replace(**extra)
        exact = exact_mean(case, scene)
        print(f"{case} {extra or ''}: {scene.n_steps} steps of {scene.dt:.3g}, {M} members in chunks of {args.chunk}", flush=True)
        mean, var, wall = chunked_moments(scene, M, args.chunk)
        out[case] = dict(mean=mean, var=var)
        z = scores(mean, var, M, exact).ravel()
        worst = int(np.nanargmax(np.abs(z)))
        print(f"| {case} | {M} | {wall:.0f} s | total {mean.sum():.4f} (exact {exact.sum():.4f}) | max |z| "
              f"{np.nanmax(np.abs(z)):.2f} (cell {worst}), rms {math.sqrt(np.nanmean(z**2)):.2f}, mean "
              f"{np.nanmean(z):+.2f} | {int((~np.isnan(z)).sum())} cells |", flush=True)
        print("  z by cell:", " ".join(f"{i}:{v:+.1f}" for i, v in enumerate(z) if not np.isnan(v)))
    if args.save:
        np.savez(args.save, **{f"{c}_{k}": v for c, d in out.items() for k, v in d.items()})


if __name__ == "__main__":
    main()
