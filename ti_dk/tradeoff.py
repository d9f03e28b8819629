"""``python -m ti_dk.tradeoff SCENE``: which setting of your scene meets the error you name, cheapest.

Runs a pilot of your scene (the same grid and physics, fewer members, a horizon you may shorten):
the particle method as the reference and candidate settings (fv, gaussian, the hybrid over
threshold, buffer and sub-steps, C, f32; --try adds your own). For every per-cell moment (mean,
variance, skewness, kurtosis) it measures each setting's bias against the particles with its
standard error, in standard errors of a run of --ensemble members (or relative), prints the table,
writes tradeoff.csv, tradeoff.h5 and tradeoff.png (cost against error, the Pareto front) to --out,
and with --accuracy Z (or --rel-error R) names the cheapest setting that meets it and writes it to
--out as a scene file you run as it is.

Exit status: 0 done; 2 bad input (one line saying what to change); 1 a run failed; 130/143 stopped.
"""
from __future__ import annotations

import argparse
import sys

from .control import runtime
from .control.cli import guarded, parser, scene_of, warn
from .control.tradeoff import ABOVE, BELOW, BUDGET, Candidate, tradeoff


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line ``argv`` (default ``sys.argv[1:]``) parsed: the scene's arguments and the
    pilot's (the target, ``--try``, the pilot's size and horizon, the cells and times scored)."""
    p = parser("python -m ti_dk.tradeoff", __doc__, "output directory for tradeoff.csv, .h5, .png and the pick",
               ensemble="the ensemble you plan to run: errors are in its standard errors (default: the scene's)")
    target = p.add_mutually_exclusive_group()
    target.add_argument("--accuracy", type=float, metavar="Z",
                        help="pick the cheapest setting whose worst moment's bias is at most Z standard errors")
    target.add_argument("--rel-error", type=float, metavar="R", help="pick by relative bias instead (0.01: 1%%)")
    p.add_argument("--try", dest="tries", action="append", default=[], metavar="'KEY=VALUE ...'",
                   help="a setting of your own, e.g. --try 'method=hybrid threshold=3 buffer=2' (repeatable)")
    p.add_argument("--no-defaults", action="store_true", help="run only the particles and the --try settings")
    p.add_argument("--pilot-ensemble", type=int, metavar="M",
                   help="members of the pilot (default: what fits --budget, at least 40)")
    p.add_argument("--pilot-t-end", type=float, metavar="T", help="a shorter horizon for the pilot")
    p.add_argument("--budget", type=float, default=BUDGET, metavar="SECONDS",
                   help="the pilot's time by the work estimates, when --pilot-ensemble is not given")
    p.add_argument("--below", type=float, default=BELOW, metavar="PPC",
                   help="score the cells whose mean (particles per cell) is below this")
    p.add_argument("--above", type=float, default=ABOVE, metavar="PPC",
                   help="and above this (emptier cells hold too few particles for a pilot to see)")
    p.add_argument("--times", type=float, nargs="+", metavar="T",
                   help="score these output times (default: all after 0)")
    return p.parse_args(argv)


def _run(args: argparse.Namespace) -> int:
    scene, caught, _ = scene_of(args)
    warn(caught)
    tries = [Candidate.parse(t) for t in args.tries]
    runtime.init(args.arch, args.threads)
    result = tradeoff(scene, planned=args.ensemble, accuracy=args.accuracy, rel_error=args.rel_error, tries=tries,
                      defaults=not args.no_defaults, pilot_ensemble=args.pilot_ensemble, pilot_t_end=args.pilot_t_end,
                      below=args.below, above=args.above, times=args.times, budget=args.budget,
                      progress=not args.no_progress, out=args.out)
    print(result.report())
    print(f"wrote: {args.out}/tradeoff.csv, tradeoff.h5, tradeoff.png"
          + (f", {scene.name}_pick.toml (run it: python -m ti_dk.scene {args.out}/{scene.name}_pick.toml)"
             if result.pick_scene is not None else ""))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m ti_dk.tradeoff``: the pilot on the scene ``argv`` names; returns the exit status
    (module docstring)."""
    return guarded(lambda: parse_args(argv), _run)


if __name__ == "__main__":
    sys.exit(main())
