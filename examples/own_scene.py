"""A scene of your own: written as a TOML file in a temporary folder, loaded, run with the hybrid
(its files written only with ``--out``).

The scene of the tutorial (docs/tutorial-scene.md): a 2D box whose middle holds a disk of low
density (2 particles per cell) in a bulk of 30, fed by a reservoir of 30 particles per cell on the
left wall and closed by a wall on the right; periodic along y. The hybrid covers the disk with
real particles (``threshold = 6``) and follows it as it fills.

    python examples/own_scene.py [--small] [--out DIR]
"""
import argparse
import tempfile
from pathlib import Path

import ti_dk

SCENE = """
name = "lowdisk2d"
description = "A low-density disk in a bulk, fed by a reservoir on the left wall"

[grid]
cells = [64, 64]
lengths = [1.0, 1.0]
boundary = [["dirichlet", "neumann"], "periodic"]   # x: reservoir left, wall right; y: periodic
reservoir_ppc = [[30, 0], 0]                         # the left reservoir holds 30 particles per cell

[init]
name = "expression"  # particles per cell as a formula in x, y (z): 30 in the bulk, 2 in a disk of radius 0.2
density = "30 - 28*step(0.2 - sqrt((x-0.5)**2 + (y-0.5)**2))"

[time]
C = 0.0625
t_end = 0.002

[method]
name = "hybrid"
seed = 7

[hybrid]
threshold = 6.0
regrid_interval = 10
regrid_floor = 0.6
buffer = 1

[stats]
output_times = [0.0005, 0.001]
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="16 x 16 cells to t = 0.0005: seconds")
    ap.add_argument("--out", help="write the run's files (run file, frames, snapshots) here (default: none)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lowdisk2d.toml"
        path.write_text(SCENE)
        small = dict(cells=[16, 16], t_end=0.0005, output_times=[]) if args.small else {}
        scene = ti_dk.load_scene(path, **small)  # keyword arguments override keys, as --set does
        print(f"{scene.name}: {scene.description}; {scene.grid.cells} cells, {scene.n_steps} steps")
        result = ti_dk.run(scene, out=args.out, progress=False, overwrite=True)  # out=None: in memory only
        ppc = result.final_density[0] * result.cell_volume
        last = result.regrids[-1]
        print(f"particles: {ppc.sum():,.1f} at the end, {scene.initial_ppc.sum():,.1f} at the start "
              f"(the reservoir's net inflow: {result.diagnostics['boundary_inflow'].sum():+,.1f})")
        print(f"particle region: {last['covered_cells']} cells in {last['boxes']} boxes after "
              f"{len(result.regrids)} regrids; lowest cell {ppc.min():.2f} particles; "
              f"negative cells in any step: {int(result.diagnostics['negative_cells'].max())}")
        if args.out:
            print("wrote:", *(f"  {p}" for p in result.written.values()), sep="\n")
        else:
            print("nothing written (the run was kept in memory): --out DIR writes its files")


if __name__ == "__main__":
    main()
