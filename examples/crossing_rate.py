"""The double well's crossing rate in one command, with its standard error, against the exact rate.

``doublewell2d`` ships with two observables, ``left = "x < 0.5"`` and ``right = "x > 0.5"``: the
particles in each well, per member, every ``sample_every`` steps. ``ti_dk.crossing_rate`` turns
them into the rate over the barrier: per member, f = N_right / (N_left + N_right) and the slope of
−ln(1 − 2f)/2 on t ≥ 0.01 (the symmetric two-state model; the blob has relaxed in its well by
then), mean ± standard error over the members. U and the start are separable and the particles
move each axis on their own, so the particle method's f(t) is that of a 1D walk along x, whose mean
is computed exactly (``ti_dk.core.theory.walk_crossing_fraction``, as ``benchmarks/kramers1d.py``
does: 0.1120 at 32 cells, C = 0.02). The default runs the 2D scene's particle method at 32×32
(8 members, a few minutes); ``--small`` the x part alone at 16 cells (40 members, seconds).

    python examples/crossing_rate.py [--small] [--method particle|hybrid|fv]
"""
import argparse
import warnings

import ti_dk
from ti_dk.core import theory
from ti_dk.output.series import two_state_rate
from ti_dk.core.expr import Potential, derivative, numpy_value

U_X = "2*(x-0.3)**2*(x-0.7)**2/5e-4"  # the scene's U along x (its y part is the same in both wells)

BLOB = {1: "exp(-((x-0.3)**2*(x-0.7)**2)/5e-4)*step(x-0.2)*step(0.4-x)",  # the scene's start, along x
        2: "exp(-((x-0.3)**2*(x-0.7)**2 + (y-0.5)**4)/5e-4)*step(x-0.2)*step(0.4-x)*step(y-0.25)*step(0.75-y)"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="the 1D x part at 16 cells, 40 members: seconds")
    ap.add_argument("--method", default="particle", help="particle (default), hybrid or fv")
    args = ap.parse_args()
    if args.small:  # 2500 particles a member at the blob's centre cell
        size = dict(cells=[16], potential=U_X, density=f"2500*{BLOB[1]}", ensemble=40,
                    sample_every=64, seed=5)
    else:  # the scene's 4e6 e^-V particles per unit volume, on 32 x 32 cells
        size = dict(cells=[32, 32], density=f"{4e6 / 32**2!r}*{BLOB[2]}", ensemble=8, sample_every=128)
    with warnings.catch_warnings():  # the drift by the empty walls passes a cell: the clamp warning
        warnings.simplefilter("ignore")
        scene = ti_dk.load_scene("doublewell2d", method=args.method, compare=None, C=0.02, t_end=0.05,
                                 output_times=[], **size)
    result = ti_dk.run(scene, progress=False)  # out="runs" writes the file; crossing_rate reads it too

    rate = ti_dk.crossing_rate(result, "left", "right", t_from=0.01)
    t = result.series["time"]
    start = scene.initial_ppc.reshape(scene.grid.cells[0], -1).sum(axis=1)  # particles per column of x
    du = derivative(Potential.of(U_X, 1).tree, 0)  # U'(x)
    f = theory.walk_crossing_fraction(lambda x: numpy_value(du, (x,)), start, scene.dt, t,
                                      sub=128 if args.small else 256)
    exact = float(two_state_rate(t, f, 0.01))
    print(f"doublewell2d, {args.method}, {'x'.join(map(str, scene.grid.cells))} cells, {rate.members} members, "
          f"{len(t)} records to t = {t[-1]:.4g}")
    print(f"crossing rate left -> right: {rate}")
    print(f"exact (the 1D walk of the particles): {exact:.4f}; (rate - exact)/SE = {(rate.value - exact) / rate.se:+.2f}")


if __name__ == "__main__":
    main()
