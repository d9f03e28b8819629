"""S(k) of particles, fv and gaussian against their exact theory in 1D and 2D (issue 28, part 4).

Six runs from the uniform state on a periodic unit box (``structure_factor = true``, 300 steps,
rows over the ensemble only, so the samples are independent): particles started exactly uniform
(S = 1), gaussian at 5 and fv at 50 particles per cell (the linear scheme's
:func:`ti_dk.core.theory.linear_structure_factor` at step 300). Prints, per run, the z of every
independent mode k ≠ 0 against the exact answer (max |z|, mean z·√K, mean z²) and writes the six
PNGs side by side to ``renders/gallery/structure_factor.png``.

    python benchmarks/structure_factor.py [--out renders/structure_factor]
"""
import argparse
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

import ti_dk
from ti_dk import load_scene, run
from ti_dk.core import spectra
from ti_dk.output.spectra import exact_structure_factor

CASES = [  # method, cells, members, particles per cell, C, extra keys
    ("particle", [64], 2000, 10, 0.0625, dict(particle_init="exact_uniform")),
    ("gaussian", [64], 2000, 5, 0.25, {}),
    ("fv", [64], 2000, 50, 0.25, {}),
    ("particle", [32, 32], 400, 10, 0.0625, dict(particle_init="exact_uniform")),
    ("gaussian", [32, 32], 400, 5, 0.2, {}),
    ("fv", [32, 32], 400, 50, 0.2, {}),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="renders/structure_factor")
    ap.add_argument("--steps", type=int, default=300)
    args = ap.parse_args()
    ti_dk.init("cpu")
    pngs = []
    for method, cells, members, ppc, C, extra in CASES:
        dx = 1.0 / cells[0]
        scene = load_scene("equilibrium1d", name=f"sk{len(cells)}d", method=method, cells=cells, ensemble=members,
                           ppc=ppc, C=C, t_equil=None, histogram=None, t_end=args.steps * C * dx * dx,
                           structure_factor=True, **extra)
        t0 = time.perf_counter()
        res = run(scene, out=args.out, snapshots=False, overwrite=True)
        S, n = res.stats.structure_factor[-1], int(res.stats.n_samples[-1])
        exact, _ = exact_structure_factor(scene, scene.n_steps)
        use = spectra.independent_modes(tuple(cells))
        use.flat[0] = False
        z = (S[use] - exact[use]) / (exact[use] * spectra.relative_se(tuple(cells), n)[use])
        print(f"{method:8s} {'x'.join(map(str, cells)):6s} {members:5d} members  {z.size:4d} modes  "
              f"max|z| {np.abs(z).max():.2f}  mean z·√K {z.mean() * np.sqrt(z.size):+.2f}  "
              f"mean z² {np.mean(z**2):.3f}  exact S {exact[use].min():.3f}–{exact[use].max():.3f}  "
              f"{time.perf_counter() - t0:.1f} s (statistics {res.timing['statistics']:.2f} s)", flush=True)
        pngs.append(iio.imread(res.written["structure factor"])[..., :3])
    rows = [np.concatenate(pngs[i:i + 3], axis=1) for i in (0, 3)]
    path = Path("renders/gallery/structure_factor.png")
    iio.imwrite(path, np.concatenate(rows, axis=0))
    print("wrote", path)


if __name__ == "__main__":
    main()
