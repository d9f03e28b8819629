"""Reading what a run writes: the HDF5 run file and the openPMD snapshots, with h5py alone.

Runs a small ``ellipse2d`` (the hybrid with ``fv`` beside it) into a folder, then reads back:
the scene and provenance attributes, the statistics rows (number density, so times the cell
volume for particles per cell), the per-step diagnostics, the hybrid's regrid log, and the last
openPMD snapshot (density mesh, particle region, particle positions). With openpmd-viewer
installed (the ``test`` extra) it also reads the snapshot series through it. Give ``--run FILE``
to read an existing ``<scene>_<method>.h5`` instead.

    python examples/read_output.py [--small] [--out DIR] [--run renders/ellipse2d_hybrid.h5]
"""
import argparse
import json
import tempfile
from pathlib import Path

import h5py
import numpy as np


def run_file(args, tmp: str) -> Path:
    """The run file to read: ``--run``, or a fresh small ellipse2d run."""
    if args.run:
        return Path(args.run)
    import ti_dk

    cells = [32, 32] if args.small else [128, 128]
    scene = ti_dk.load_scene("ellipse2d", cells=cells, t_end=0.0004, output_times=[0.0002])
    return ti_dk.run(scene, out=args.out or tmp, progress=False, overwrite=True).path


def read_run(path: Path) -> None:
    with h5py.File(path, "r") as f:
        scene = json.loads(f.attrs["scene"])
        versions = json.loads(f.attrs["versions"])
        print(f"{path.name}: complete = {bool(f.attrs['complete'])}, ti_dk {versions['ti_dk']}, "
              f"seed {int(f.attrs['seed'])}, {f.attrs['wall_time']:.1f} s")
        print(f"  scene: {scene['grid']['cells']} cells, method {scene['method']['name']}, "
              f"threshold {scene['hybrid']['threshold']}")
        st = f["stats"]
        vol = st.attrs["cell_volume"]
        ppc = st["mean"][:] * vol  # (rows, *cells): st.attrs["units"] is number density; × V_c: particles per cell
        for t, row in zip(st["time"][:], ppc):
            print(f"  t = {t:.4g}: {row.sum():,.1f} particles, fewest in a cell {row.min():.2f}")
        d = f["diagnostics"]
        print(f"  {len(d['time'])} steps; mass {d['mass'][0]:,.1f} -> {d['mass'][-1]:,.1f}; negative cells, "
              f"most in a step: hybrid {int(d['negative_cells'][:].max())}, "
              f"fv beside it {int(d['compare_negative_cells'][:].max()) if 'compare_negative_cells' in d else '-'}")
        if "regrid" in f:
            rg = f["regrid"]
            print(f"  {len(rg['step'])} regrids, region {rg['covered_cells'][0]} -> {rg['covered_cells'][-1]} cells")


def read_snapshot(folder: Path) -> None:
    snaps = sorted(folder.glob("data*.h5"))
    with h5py.File(snaps[-1], "r") as f:
        (it,) = f["data"].keys()  # file-based: one iteration per file
        g = f[f"data/{it}"]
        rho = g["meshes/density"]
        ppc = rho[:] * np.prod(rho.attrs["gridSpacing"])
        print(f"{snaps[-1].name}: iteration {it}, t = {g.attrs['time']:.4g}, density {rho.shape}, "
              f"{ppc.sum():,.1f} particles in member 0")
        if "particle_region" in g["meshes"]:
            print(f"  particle region: {int(g['meshes/particle_region'][:].sum())} cells")
        if "particles/particles" in g:
            p = g["particles/particles"]
            x, y = p["position/x"][:], p["position/y"][:]
            print(f"  {len(x):,} particles, x in [{x.min():.3f}, {x.max():.3f}], y in [{y.min():.3f}, {y.max():.3f}]")
    try:
        from openpmd_viewer import OpenPMDTimeSeries
    except ImportError:
        return
    ts = OpenPMDTimeSeries(str(folder), check_all_files=False)
    field, info = ts.get_field("density", iteration=ts.iterations[-1])
    print(f"  openpmd-viewer: iterations {[int(i) for i in ts.iterations]}, density {field.shape}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="a 32 x 32 run: seconds")
    ap.add_argument("--out", help="where the run's files go (default: a temporary folder)")
    ap.add_argument("--run", help="read this run file instead of running")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = run_file(args, tmp)
        read_run(path)
        snapshots = path.with_name(path.stem + "_openpmd")
        if snapshots.is_dir():
            read_snapshot(snapshots)


if __name__ == "__main__":
    main()
