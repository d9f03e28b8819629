"""openPMD snapshots read back by a third-party reader (openPMD-viewer); the recorded version."""
import json
import os
import sys

import h5py
import pytest
import numpy as np
from openpmd_viewer import OpenPMDTimeSeries

import ti_dk
from ti_dk import load_scene, run

from ..helpers import ROOT, file_tree

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


def test_openpmd_units_are_pure_numbers_of_l_unless_l_and_d_are_given_in_si(tmp_path):
    """Without length_si the snapshot claims no metres (unitDimension 0, and says so in words); with
    L = 2 µm and D = 1e-12 m²/s a third-party reader converts lengths to metres, densities to m^-2
    and times to seconds (the unit L²/(2D) = 2 s)."""
    common = dict(cells=[16, 16], t_end=0.0005, compare="none", output_times=[0.0005], regrid_interval=3)
    plain, si = tmp_path / "plain", tmp_path / "si"
    res = run(load_scene("ellipse2d", **common), out=plain, frames=False)
    scene = load_scene("ellipse2d", length_si=2e-6, diffusion_si=1e-12, **common)
    run(scene, out=si, frames=False)
    name = f"ellipse2d_hybrid_openpmd/data{scene.n_steps:06d}.h5"
    with h5py.File(plain / name) as f:
        rho = f[f"data/{scene.n_steps}/meshes/density"]
        assert rho.attrs["unitSI"] == 1.0 and not rho.attrs["unitDimension"].any()
        assert not f[f"data/{scene.n_steps}/particles/particles/position"].attrs["unitDimension"].any()
        assert "units of the scene's L" in f.attrs["ti_dk_units"].decode()
    with h5py.File(si / name) as f:
        assert f.attrs["ti_dk_units"].decode() == "lengths in L = 2e-06 m; times in L^2/(2D) = 2 s"
    a, b = (OpenPMDTimeSeries(str(d / "ellipse2d_hybrid_openpmd")) for d in (plain, si))
    (rho_a, info_a), (rho_b, info_b) = (ts.get_field("density", iteration=scene.n_steps) for ts in (a, b))
    assert np.array_equal(rho_a, res.final_density[0]) and np.allclose(rho_b, rho_a / 4e-12, rtol=1e-12)
    assert np.isclose(info_b.dx, 2e-6 / 16) and np.isclose(info_a.dx, 1 / 16)
    assert np.allclose(b.t, a.t * 2.0) and np.isclose(a.t[-1], scene.n_steps * scene.dt)
    (xa,), (xb,) = (ts.get_particle(["x"], species="particles", iteration=scene.n_steps) for ts in (a, b))
    assert len(xa) > 0 and np.allclose(xb, xa * 2e-6)  # the same seed: the same particles


def test_diffusion_si_without_length_si_is_refused():
    with pytest.raises(ti_dk.ConfigError, match="diffusion_si = 1e-09 without length_si"):
        load_scene("ellipse2d", diffusion_si=1e-9)


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
    from ti_dk.output.claim import Outputs

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
    from ti_dk.output.claim import Outputs
    from ti_dk.output.files import frame_file, pack_ids

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
    from ti_dk.output.claim import Outputs
    from ti_dk.output.files import RunFile

    scene = load_scene("void1d", ensemble=2, cells=[4], histogram=[0, 3])
    rf = RunFile.of(Outputs.of(tmp_path, scene), scene)
    row = {"mean": np.ones(4), "n_samples": 2, "histogram": np.zeros((4, 4), dtype=np.int64)}
    rf.write_rows([0.0, 0.5], [row, row])
    rf.annotate("timing", {"io": 1.0})
    rf.close(1.0)
    with h5py.File(rf.at) as f:
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
# -- hostile outputs: links, foreign files, failed replaces, locks --------------------------------
def _scene2d(cells=16, t_end=0.002):
    """A 2D scene cheap enough to run many times: a run file, frames and snapshots."""
    return load_scene("ellipse2d", method="fv", compare="none", cells=[cells, cells], t_end=t_end,
                      output_times=[0.0, 0.001])


@pytest.fixture
def finished(tmp_path):
    """A complete result (run file, frames, snapshots) in tmp_path/out and the tree of its bytes."""
    out = tmp_path / "out"
    run(_scene2d(), out=out)
    tree = file_tree(out)
    assert any("frames/frame_" in k for k in tree) and any("openpmd/data" in k for k in tree), tree
    return out, tree


def _shape(out):
    with h5py.File(out / "ellipse2d_fv.h5") as f:
        return f["stats/mean"].shape[1:], bool(f.attrs["complete"])


@pytest.mark.parametrize("part", ["run_file", "frames", "snapshots", "checkpoint", "lock", "stage", "movie"])
@pytest.mark.parametrize("inside", [True, False])
def test_a_link_at_any_output_path_is_refused_and_its_target_untouched(tmp_path, part, inside):
    from ti_dk import ConfigError
    from ti_dk.output.claim import Outputs

    out = tmp_path / "out"
    out.mkdir()
    target = (out if inside else tmp_path) / "precious.h5"
    target.write_bytes(b"precious bytes")
    link = getattr(Outputs.of(out, _scene2d()), part)
    link.symlink_to(target)
    with pytest.raises(ConfigError, match="is a symbolic link: ti_dk never writes through links"):
        run(_scene2d(), out=out, overwrite=True, checkpoint_every=5)
    assert target.read_bytes() == b"precious bytes" and link.is_symlink()
    assert sorted(p.name for p in out.iterdir()) == sorted({"precious.h5", link.name} if inside else {link.name})


@pytest.mark.parametrize("what, message", [
    ("text", "is not a ti_dk run file"),
    ("hdf5", "is not a ti_dk run file"),
    ("empty", "is not a ti_dk run file"),
    ("folder", "is a folder that ti_dk did not write"),
    ("frames_file", "is a file that ti_dk did not write"),
])
@pytest.mark.parametrize("overwrite", [False, True])
def test_a_foreign_file_at_the_run_path_is_refused_even_with_overwrite(tmp_path, what, message, overwrite):
    from ti_dk import ConfigError

    out = tmp_path / "out"
    out.mkdir()
    path = out / ("ellipse2d_fv_frames" if what == "frames_file" else "ellipse2d_fv.h5")
    if what == "hdf5":
        with h5py.File(path, "w") as f:
            f["data"] = np.arange(5)
            f.attrs["complete"] = True  # says complete, but is not ours
    elif what == "folder":
        path.mkdir()
        (path / "notes.txt").write_text("mine")
    elif what != "empty":
        path.write_text("my notes, not a run")
    else:
        path.touch()
    before = file_tree(out)
    with pytest.raises(ConfigError, match=message):
        run(_scene2d(), out=out, overwrite=overwrite)
    assert file_tree(out) == before and sorted(p.name for p in out.iterdir()) == [path.name]


def _failing(monkeypatch, where, after):
    """Make ``where`` fail with an I/O error from its ``after``-th call on: ENOSPC for the space check
    before every write, EACCES for the frame writer, ENOSPC for the lock's pid."""
    import errno

    from ti_dk.output import claim, files, render

    calls = {"n": 0}
    target, name, code = {"space": (files, "require_space", errno.ENOSPC),
                          "frames": (render.FrameWriter, "write", errno.EACCES),
                          "lock": (claim.os, "pwrite", errno.ENOSPC)}[where]
    real = getattr(target, name)

    def fail(*args, **kw):
        calls["n"] += 1
        if calls["n"] > after:
            raise OSError(code, os.strerror(code), "injected")
        return real(*args, **kw)

    monkeypatch.setattr(target, name, fail)
    return calls


@pytest.mark.parametrize("where, after", [("space", 0), ("space", 3), ("space", 8), ("frames", 0), ("frames", 2),
                                          ("lock", 0)])
def test_a_failed_overwrite_leaves_the_old_result_byte_identical(finished, monkeypatch, where, after):
    """Disk full at the start or half-way, permission denied for a frame, disk full while locking."""
    from ti_dk.output.files import OutputError

    out, before = finished
    calls = _failing(monkeypatch, where, after)
    with pytest.raises(OutputError) as err:
        run(_scene2d(8), out=out, overwrite=True)
    assert calls["n"] > after  # it did fail where asked
    assert "\n" not in str(err.value) and ("free space" in str(err.value)) == (where != "frames"), str(err.value)
    assert file_tree(out) == before  # no lock, no stage, nothing of the new run
    monkeypatch.undo()
    run(_scene2d(8), out=out, overwrite=True)  # a successful one replaces them all
    after_tree = file_tree(out)
    assert _shape(out) == ((8, 8), True)
    assert {k.split("/")[0] for k in after_tree} == {k.split("/")[0] for k in before}  # the same parts, all new
    assert not set(after_tree.items()) & set(before.items()), "every file of the old result replaced"
    for p in (out / "ellipse2d_fv_openpmd").glob("data*.h5"):
        with h5py.File(p) as f:
            assert f[f"data/{next(iter(f['data']))}/meshes/density"].shape == (8, 8)


def test_a_reader_holding_the_old_file_neither_blocks_nor_sees_a_torn_replace(finished):
    """Another process reads the old result (HDF5's own file lock held) all through the replace."""
    import subprocess

    out, before = finished
    script = ("import sys, h5py; f = h5py.File(sys.argv[1], 'r'); old = f['stats/mean'][()].tobytes(); "
              "print('open', flush=True); sys.stdin.readline(); "
              "print(f['stats/mean'][()].tobytes() == old and bool(f.attrs['complete']), flush=True)")
    reader = subprocess.Popen([sys.executable, "-c", script, str(out / "ellipse2d_fv.h5")], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert reader.stdout.readline() == "open\n"
        res = run(_scene2d(8), out=out, overwrite=True)
        reader.stdin.write("\n")
        reader.stdin.flush()
        assert reader.stdout.readline() == "True\n"  # the old file, whole, to the end of its reading
    finally:
        reader.kill()
        reader.wait()
    assert res.path == out / "ellipse2d_fv.h5" and _shape(out) == ((8, 8), True)
    assert not [p for p in out.iterdir() if p.name.startswith(".") or p.suffix == ".lock"]


def test_a_stopped_replace_keeps_the_old_result_and_its_restart_finishes_bit_for_bit(finished, tmp_path,
                                                                                        monkeypatch):
    import signal

    from ti_dk.control import handlers
    from ti_dk.control.signals import Stopped, stop_on_signals

    out, before = finished
    scene = _scene2d(8, t_end=0.01)  # 10 steps
    whole = run(scene, out=tmp_path / "whole", checkpoint_every=3)
    write = handlers.Checkpoints.write

    def stop_after(self, n):  # SIGTERM right after the first checkpoint
        write(self, n)
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(handlers.Checkpoints, "write", stop_after)
    with stop_on_signals(), pytest.raises(Stopped, match="stopped by SIGTERM at step 3") as err:
        run(scene, out=out, overwrite=True, checkpoint_every=3)
    assert "is marked incomplete" not in str(err.value)  # the complete one in place is kept
    monkeypatch.undo()
    tree = file_tree(out)
    assert {k: v for k, v in tree.items() if not k.startswith((".", "ellipse2d_fv_checkpoint"))} == before
    with h5py.File(out / ".ellipse2d_fv.partial" / "ellipse2d_fv.h5") as f:  # what the stopped run wrote
        assert not f.attrs["complete"] and f["diagnostics/time"].shape == (3,)  # flushed up to the stop
    res = run(scene, out=out, overwrite=True, restart=out / "ellipse2d_fv_checkpoint.h5")
    assert np.array_equal(res.final_density, whole.final_density)
    assert np.array_equal(res.stats.mean, whole.stats.mean) and _shape(out) == ((8, 8), True)
    assert sorted(p.name for p in (out / "ellipse2d_fv_frames").iterdir()) == \
        sorted(p.name for p in (tmp_path / "whole" / "ellipse2d_fv_frames").iterdir())
    with h5py.File(res.path) as f:
        timing = json.loads(f.attrs["timing"])
        assert min(timing.values()) >= 0 and timing["total"] >= sum(v for k, v in timing.items() if k != "total")
    assert not (out / ".ellipse2d_fv.partial").exists()


def test_a_stale_lock_is_named_and_taken_over_and_every_lock_is_removed(tmp_path, capsys):
    import subprocess

    from ti_dk import ConfigError
    from ti_dk.output.claim import Outputs

    o = Outputs.of(tmp_path, load_scene("void1d"))
    o.lock.write_text("4242\n")  # left by a run that crashed
    with o.claim():
        assert o.lock.read_text() == f"{os.getpid()}\n"
    assert "was left by run pid 4242" in capsys.readouterr().err and not o.lock.exists()
    with o.claim():  # no lock left: nothing said
        pass
    assert capsys.readouterr().err == "" and not o.lock.exists()
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time; fd = os.open(sys.argv[1], "
                               "os.O_RDWR | os.O_CREAT); fcntl.flock(fd, fcntl.LOCK_EX); os.write(fd, b'777'); "
                               "print('held', flush=True); time.sleep(60)", str(o.lock)], stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline() == b"held\n"
        with pytest.raises(ConfigError, match=r"being written by another run \(pid 777\)"):
            with o.claim():
                pass
        assert o.lock.exists()  # the holder's: not removed by the refused run
    finally:
        holder.kill()
        holder.wait()



def test_a_restart_in_place_writes_no_frame_through_a_link_planted_among_the_frames(tmp_path, monkeypatch):
    import signal

    from ti_dk.control import handlers
    from ti_dk.control.signals import Stopped, stop_on_signals

    scene, out = _scene2d(8, t_end=0.01), tmp_path / "out"  # frames at steps 0, 1 and 10
    write = handlers.Checkpoints.write

    def stop_after(self, n):
        write(self, n)
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(handlers.Checkpoints, "write", stop_after)
    with stop_on_signals(), pytest.raises(Stopped, match="is marked incomplete; resume with --restart"):
        run(scene, out=out, checkpoint_every=3)
    monkeypatch.undo()
    frames = out / "ellipse2d_fv_frames"
    assert sorted(p.name for p in frames.iterdir()) == ["frame_0000.png", "frame_0001.png"]
    precious = tmp_path / "precious.png"
    precious.write_bytes(b"not yours")
    (frames / "frame_0002.png").symlink_to(precious)
    run(scene, out=out, restart=out / "ellipse2d_fv_checkpoint.h5")
    assert precious.read_bytes() == b"not yours" and not (frames / "frame_0002.png").is_symlink()
    assert _shape(out) == ((8, 8), True)


def test_the_run_file_opens_the_default_way_while_the_run_goes(tmp_path, monkeypatch):
    """Another process opens the run file with h5py's defaults (HDF5's file lock) in the middle of
    the run, reads the rows flushed so far and sees it unfinished."""
    import subprocess

    from ti_dk.control.controller import Controller

    seen, record = [], Controller.record
    script = ("import sys, h5py\nwith h5py.File(sys.argv[1], 'r') as f:\n"
              "    print(bool(f.attrs['complete']), f['stats/time'].shape[0], f['diagnostics/time'].shape[0])")

    def record_and_read(self, n):
        record(self, n)
        if n == 5:
            r = subprocess.run([sys.executable, "-c", script, str(self.rf.at)], capture_output=True, text=True)
            seen.append(r.stdout.strip() or r.stderr.strip().splitlines()[-1])

    monkeypatch.setattr(Controller, "record", record_and_read)
    scene = load_scene("void1d", cells=[32], t_end=0.002, output_times=[0.0, 0.0001, 0.002], C=0.05)
    assert scene.n_steps >= 10
    run(scene, out=tmp_path, checkpoint_every=5)  # a checkpoint flushes the diagnostics at step 5
    assert seen == ["False 2 5"], seen
