"""openPMD snapshots read back by a third-party reader (openPMD-viewer); the recorded version."""
import json
import sys

import h5py
import pytest
import numpy as np
from openpmd_viewer import OpenPMDTimeSeries

import ti_dk
from ti_dk import load_scene, run

from ..helpers import ROOT

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


def test_openpmd_round_trip(tmp_path):
    scene = load_scene("ellipse2d", cells=[24, 20], lengths=[1.2, 1.0], t_end=0.0005, compare="none",
                       output_times=[0.0, 0.0005], regrid_interval=3)
    res = run(scene, out=tmp_path, frames=False)
    ts = OpenPMDTimeSeries(str(tmp_path / "ellipse2d_hybrid_openpmd"), check_all_files=True)
    assert list(ts.iterations) == [0, scene.n_steps]
    assert np.allclose(ts.t, [0.0, scene.n_steps * scene.dt])
    assert set(ts.avail_fields) == {"density", "negative_cells", "particle_region"}
    rho, info = ts.get_field("density", iteration=scene.n_steps)
    assert np.array_equal(rho, res.final_density[0])
    assert np.allclose(info.dx, scene.grid.dx[0]) and np.allclose(info.dy, scene.grid.dx[1])
    region, _ = ts.get_field("particle_region", iteration=scene.n_steps)
    x, y, pid = ts.get_particle(["x", "y", "id"], species="particles", iteration=scene.n_steps)
    # every particle sits in a covered cell, and the covered cells hold exactly the particles
    i, j = (x // scene.grid.dx[0]).astype(int), (y // scene.grid.dx[1]).astype(int)
    assert np.all(region[i, j] == 1)
    counts = np.zeros(scene.grid.cells)
    np.add.at(counts, (i, j), 1)
    assert np.allclose(counts[region == 1], rho[region == 1] * scene.grid.cell_volume)
    assert len(np.unique(pid)) == len(pid) > 0
    with h5py.File(tmp_path / "ellipse2d_hybrid_openpmd" / f"data{scene.n_steps:06d}.h5") as f:
        boxes = f["ti_dk/boxes"][:]  # outside the openPMD base path
        assert f.attrs["openPMD"] == b"1.1.0"
        assert f.attrs["softwareVersion"].decode() == ti_dk.__version__
    covered = np.zeros(scene.grid.cells, dtype=int)
    for lo0, lo1, hi0, hi1 in boxes:
        covered[lo0:hi0, lo1:hi1] += 1
    assert np.array_equal(covered, region)


def test_version_is_the_one_in_pyproject(tmp_path):
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert ti_dk.__version__ == pyproject["project"]["version"]
    res = run(load_scene("void1d", ensemble=2, t_end=0.0001), out=tmp_path)
    with h5py.File(res.path) as f:
        assert json.loads(f.attrs["versions"])["ti_dk"] == ti_dk.__version__


def test_snapshots_pass_the_openpmd_validator(tmp_path):
    """openPMD's own checker (openpmd-validator, openPMD_check_h5): 0 errors for every snapshot."""
    check = pytest.importorskip("openpmd_validator.check_h5")
    scene = load_scene("ellipse2d", cells=[16, 16], t_end=0.001, compare="none", output_times=[0.0, 0.0005])
    run(scene, out=tmp_path, frames=False)
    snaps = sorted((tmp_path / "ellipse2d_hybrid_openpmd").glob("data*.h5"))
    assert len(snaps) == 3
    for p in snaps:
        errors, warnings = check.check_file(str(p))
        assert errors == 0, p.name


def test_outputs_stay_inside_out_and_lock_one_run(tmp_path):
    from ti_dk import ConfigError
    from ti_dk.output.files import Outputs

    scene = load_scene("void1d")
    o = Outputs.of(tmp_path, scene)
    paths = [o.run_file, o.frames, o.snapshots, o.checkpoint, o.chunks, o.lock]
    assert all(p.parent == tmp_path and p.name.startswith("void1d_fv") for p in paths)
    with o.claim():
        with pytest.raises(ConfigError, match="being written by another run"):
            with Outputs.of(tmp_path, scene).claim():
                pass
    with o.claim():  # released
        pass


def test_chunk_and_frame_names_and_openpmd_ids(tmp_path):
    from ti_dk.output.files import Outputs, frame_file, pack_ids

    o = Outputs.of(tmp_path, load_scene("void1d"))
    assert o.chunk(12).parent == o.chunks and o.chunk(12).name == "chunk_000000012.h5"
    o.chunks.mkdir()
    for m0 in (40, 0):
        o.chunk(m0).touch()
    assert o.chunk_files() == [o.chunk(0), o.chunk(40)]
    assert frame_file(o.frames, 3) == o.frames / "frame_0003.png"
    pid = np.array([[1, 2], [2**32 - 1, 0]], dtype=np.uint32)
    assert pack_ids(pid).tolist() == [(1 << 32) | 2, (2**32 - 1) << 32]


def test_run_file_rows_and_attributes(tmp_path):
    from ti_dk.output.files import Outputs, RunFile

    scene = load_scene("void1d", ensemble=2, cells=[4], histogram=[0, 3])
    rf = RunFile.of(Outputs.of(tmp_path, scene), scene)
    row = {"mean": np.ones(4), "n_samples": 2, "histogram": np.zeros((4, 4), dtype=np.int64)}
    rf.write_rows([0.0, 0.5], [row, row])
    rf.annotate("timing", {"io": 1.0})
    rf.close(1.0)
    with h5py.File(rf.path) as f:
        assert f["stats/time"][:].tolist() == [0.0, 0.5] and f["stats/histogram"].shape == (2, 4, 4)
        assert json.loads(f.attrs["timing"]) == {"io": 1.0} and f.attrs["complete"]


def _datasets(f):
    found = []
    f.visititems(lambda name, obj: found.append(name) if isinstance(obj, h5py.Dataset) else None)
    return found


def test_every_dataset_states_its_units_and_one_member_omits_the_ensemble_only_moments(tmp_path):
    """A one-member hybrid run beside fv, with frames and a histogram: every dataset has a ``units``
    attribute, the documented conventions hold (mean per unit volume: the initial particles per
    cell over the cell volume; mass: particles), and the ensemble-only moments are named and left
    out; an ensemble run writes them and sums its diagnostics over the members."""
    from ti_dk.output.files import RunFile
    from ti_dk.output.units import UNITS

    scene = load_scene("ellipse2d", cells=[16, 16], t_end=0.0005, output_times=[0.0], histogram=[0, 40])
    res = run(scene, out=tmp_path, snapshots=False)
    with h5py.File(res.path) as f:
        names = _datasets(f)
        assert {"diagnostics/compare_mass", "regrid/created", "frames/negative_cells", "stats/histogram"} <= set(names)
        assert all("units" in f[n].attrs for n in names), [n for n in names if "units" not in f[n].attrs]
        assert f["diagnostics/mass"].attrs["units"] == "particles (sum over members)"
        assert "non-excess" in UNITS["stats/kurtosis"]
        assert f["diagnostics/compare_mass"].attrs["units"] == "particles (sum over members); of the compared method"
        st = f["stats"]
        assert st.attrs["ensemble_only"] == "variance skewness kurtosis" == st.attrs["omitted"]
        assert "variance" not in st and "kurtosis" not in st
        vol = st.attrs["cell_volume"]
        assert np.allclose(st["mean"][0] * vol, scene.initial_ppc)  # t = 0: per unit volume
        assert np.isclose(f["diagnostics/mass"][-1], res.final_density.sum() * vol)  # particles
    doc = RunFile.__doc__
    assert all(k.split("/")[1] in doc for k in UNITS) and "ensemble_only" in doc and "non-excess" in doc

    scene = load_scene("void1d", ensemble=3, cells=[20], t_end=0.0005)
    res = run(scene, out=tmp_path / "e", frames=False)
    with h5py.File(res.path) as f:
        assert f["stats"].attrs["omitted"] == "" and {"variance", "skewness", "kurtosis"} <= set(f["stats"])
        assert f["stats/kurtosis"].attrs["units"] == UNITS["stats/kurtosis"]
        mass = f["diagnostics/mass"][-1]
        assert np.isclose(mass, res.final_density.sum() * scene.grid.cell_volume)  # all three members
        assert mass > 2.5 * res.final_density[0].sum() * scene.grid.cell_volume
