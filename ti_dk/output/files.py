"""HDF5 record of a run: statistics rows, per-step diagnostics and provenance."""
from __future__ import annotations

import errno
import json
import math
import os
import platform
import re
import resource
import tempfile
import time
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path

import h5py
import numpy as np

from ..core.errors import OutputError
from .units import units_of
STAT_KEYS = ("mean", "variance", "skewness", "kurtosis")


def package_version() -> str:
    """ti_dk's version from its installed metadata (pyproject.toml), without importing the package root."""
    try:
        return metadata.version("ti_dk")
    except metadata.PackageNotFoundError:  # a source tree that was never pip-installed
        return "unknown"


def output_error(path: Path, exc: OSError) -> OutputError:
    """The one-line message for an I/O failure on ``path``, saying what to change."""
    why = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
           errno.EACCES: "permission denied", errno.EROFS: "the file system is read-only",
           errno.EFBIG: f"the file would pass this process's file size limit (ulimit -f: {_size_limit()} bytes)"}
    code = exc.errno
    if code is None:  # HDF5 reports the system error inside its message: "... errno = 28, ..."
        found = re.search(r"errno = (\d+)", str(exc))
        code = int(found.group(1)) if found else None
    reason = why.get(code) or exc.strerror or str(exc).splitlines()[0]
    remedy = "free space or give another --out" if code in (errno.ENOSPC, errno.EDQUOT) else \
        "raise the limit (ulimit -f unlimited) or write less (fewer output times, members or cells)" \
        if code == errno.EFBIG else \
        "give another --out" if code == errno.ENAMETOOLONG else "give a directory you can write with --out"
    return OutputError(f"cannot write {path}: {reason}; {remedy}")


SPACE_RESERVE = 1 << 20  # bytes kept free on the output's file system (HDF5 metadata, the closing flush)


def require_space(path: Path, nbytes: float) -> None:
    """Raise ENOSPC *before* writing ``nbytes`` near ``path`` would leave less than ``SPACE_RESERVE``,
    and EFBIG before it would bring the file ``path`` (a new one, if a folder) within
    ``SPACE_RESERVE`` of the process's file size limit (``ulimit -f``, ``RLIMIT_FSIZE``).

    HDF5 cannot recover from a write that fails for want of space: its metadata cache retries the
    flush forever and the process can crash when the file is released. Refusing the write first
    keeps every file closable (and marked incomplete).
    """
    folder = path if path.is_dir() else path.parent
    st = os.statvfs(folder)
    if st.f_bavail * st.f_frsize < nbytes + SPACE_RESERVE:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    size = path.stat().st_size if path.is_file() else 0
    if size + nbytes + SPACE_RESERVE > _size_limit():
        raise OSError(errno.EFBIG, os.strerror(errno.EFBIG), str(path))


def _size_limit() -> float:
    """The largest file this process may write, in bytes (``ulimit -f``; inf without a limit)."""
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return math.inf if limit == resource.RLIM_INFINITY else limit


def frame_file(directory: Path, k: int) -> Path:
    """The ``k``-th PNG frame in a frames folder (``Outputs.frames``)."""
    return directory / f"frame_{k:04d}.png"


def is_complete(path: Path) -> bool:
    """Whether ``path`` is a run file marked complete (False for a missing or unreadable one)."""
    try:
        with h5py.File(path, "r", locking=False) as f:
            return bool(f.attrs.get("complete", False))
    except (OSError, ValueError):
        return False


def versions() -> dict[str, str]:
    """The versions of ti_dk, Taichi, NumPy, h5py and Python, as every run file records them."""
    import taichi

    return {"ti_dk": package_version(), "taichi": ".".join(map(str, taichi.__version__)), "numpy": np.__version__,
            "h5py": h5py.__version__, "python": platform.python_version()}


class RunFile:
    """One run's HDF5 file.

    Layout: attributes ``scene`` (JSON), ``versions`` (JSON), ``seed``, ``complete``,
    ``wall_time``, ``timing``, ``movie_bytes`` (with a movie: its size, which marks it as this
    run's); ``/stats/time``, ``/stats/n_samples`` and
    ``/stats/{mean,variance,skewness,kurtosis}`` shaped ``(n_rows, *cells)``, optional
    ``/stats/histogram`` ``(n_rows, *cells, bins)`` with attribute ``lo`` and
    ``/stats/histogram_outside``, optional ``/stats/structure_factor`` ``(n_rows, *half cells)``
    (:mod:`ti_dk.core.spectra`; attributes ``definition``, ``k0``, ``k1``, …: the wave numbers per
    axis); ``/diagnostics/{time,mass,min_density,negative_cells,
    boundary_inflow,clamped_steps}`` one entry per step (hybrid: also ``particles`` and
    ``regrid_change``; a compared method: ``compare_{mass,min_density,negative_cells}``);
    ``/regrid/{step,boxes,covered_cells,efficiency,created,removed,on_demand}`` one entry per
    regrid of a hybrid run; ``/frames/{time,negative_cells}`` one entry per frame;
    ``/series/{time,mass,negative_cells}`` (a region solver: also ``particles``, ``region_cells``)
    and ``/observables/{time,<name>}`` (the scene's ``[observables]``) per member, shaped
    ``(records, members)``, one record every ``scene.observe_every`` steps, step 0 and the last.

    Units: every dataset carries a ``units`` attribute (:data:`ti_dk.output.units.UNITS`). The
    statistics are of the number density, per unit volume (``/stats`` attribute ``cell_volume``
    turns them into particles per cell); skewness κ3/κ2^{3/2} and kurtosis κ4/κ2² + 3
    (non-excess: 3 for a Gaussian) are dimensionless; histograms and frames count particles per
    cell. Diagnostics and regrid records are sums over the ensemble's members (``min_density``
    is the minimum over members and cells): ``diagnostics/mass`` is in particles summed over
    members. Times are in L²/(2D).

    Ensemble-only: ``variance``, ``skewness`` and ``kurtosis`` need two or more densities per
    row, so a run of one member without time pooling (``t_equil`` unset) writes only ``mean``
    (that member's density) and ``n_samples``; the ``/stats`` attribute ``ensemble_only`` names
    them in every file, ``omitted`` those this file leaves out.

    Every row is flushed when written; ``complete`` turns true only at the end, so a killed run
    leaves a readable file that says it is unfinished. The file is written without HDF5's file
    lock, so that ``h5py.File(path, "r")`` opens it while the run goes (a reader sees the rows
    flushed before it opened the file: open, read and close again for newer ones).
    """

    def __init__(self, path: Path, scene, histogram_bins: int | None = None, at: Path | None = None):
        self.path = path  # the run file's name (where it lies once the run ends)
        self.at = at or path  # where it is written (``Outputs.staged``)
        self.at.parent.mkdir(parents=True, exist_ok=True)
        require_space(self.at.parent, 64 << 10)
        self.at.unlink(missing_ok=True)  # a new file: never an old one truncated, nor a link followed
        # No HDF5 file lock: with one, a reader that opens the file the default way while the run
        # goes fails (BlockingIOError); two runs never write one file (Outputs.claim's own lock).
        self.h5 = h5py.File(self.at, "w", locking=False)
        a = self.h5.attrs
        a["scene"] = scene_json(scene)
        a["versions"] = json.dumps(versions())
        a["seed"] = np.uint64(scene.method.seed)
        a["created"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        a["complete"] = False
        st = self.h5.create_group("stats")
        st.attrs["units"] = "number density (particles per unit volume)"
        st.attrs["cell_volume"] = scene.grid.cell_volume
        self._grow(st, "time", (), np.float64)
        self._grow(st, "n_samples", (), np.int64)
        # one member and no pooling: only the mean (= that member's density) means anything
        self.keys = STAT_KEYS if scene.method.ensemble > 1 or scene.stats.t_equil is not None else STAT_KEYS[:1]
        st.attrs["ensemble_only"] = " ".join(STAT_KEYS[1:])
        st.attrs["omitted"] = " ".join(k for k in STAT_KEYS if k not in self.keys)
        for k in self.keys:
            self._grow(st, k, scene.grid.cells, np.float64)
        if histogram_bins:
            hist = self._grow(st, "histogram", (*scene.grid.cells, histogram_bins), np.int64)
            hist.attrs["lo"] = scene.stats.histogram[0]
            self._grow(st, "histogram_outside", scene.grid.cells, np.int64)
        if scene.stats.structure_factor and len(self.keys) > 1:
            self._structure_factor(st, scene.grid)
        self.diag = self.h5.create_group("diagnostics")
        self.h5.flush()

    def _structure_factor(self, st, grid) -> None:
        """The dataset of S(k), with its definition and wave numbers as attributes."""
        from ..core import spectra

        ds = self._grow(st, "structure_factor", spectra.half_shape(grid.cells), np.float64)
        ds.attrs["definition"] = ("S(k) = <|sum_j dN_j exp(-i k.x_j)|^2> / <N_total>, dN_j = N_j - <N_j> the "
                                  "particle count fluctuation of cell j; numpy rfftn half grid, k_a = 2 pi m_a / L_a")
        for a, k in enumerate(spectra.wavenumbers(grid.cells, grid.lengths)):
            ds.attrs[f"k{a}"] = k

    @classmethod
    def of(cls, outputs, scene) -> "RunFile":
        """The run file of ``outputs`` (:class:`~ti_dk.output.claim.Outputs`; written at its staged place), with as many histogram bins as
        ``scene.stats.histogram`` asks."""
        hist = scene.stats.histogram
        return cls(outputs.run_file, scene, hist[1] - hist[0] + 1 if hist else None, outputs.staged(outputs.run_file))

    @staticmethod
    def _grow(group, name, shape, dtype):
        ds = group.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                                  chunks=(1, *shape) if shape else (1024,))
        return _label(ds)

    @staticmethod
    def _append(ds, rows) -> None:
        rows = np.asarray(rows)
        n = ds.shape[0]
        ds.resize(n + rows.shape[0], axis=0)
        ds[n:] = rows

    def write_row(self, t: float, row: dict[str, np.ndarray]) -> None:
        """Append the statistics row of time ``t`` (the keys ``/stats`` holds) and flush."""
        require_space(self.at, sum(np.asarray(v).nbytes for v in row.values()))
        st = self.h5["stats"]
        self._append(st["time"], [t])
        for k, v in row.items():
            if k in st:
                self._append(st[k], np.asarray(v)[None])
        self.h5.flush()

    def write_rows(self, times, rows: list[dict[str, np.ndarray]]) -> None:
        """:meth:`write_row` for each of ``rows`` (a restarted run's, a merged ensemble's)."""
        for t, row in zip(times, rows):
            self.write_row(t, row)

    def write_diagnostics(self, diag: dict[str, list]) -> None:
        """Append per-step diagnostics (key → values, one per step) to ``/diagnostics`` and flush."""
        require_space(self.at, 8 * sum(len(v) for v in diag.values()))
        for k, v in diag.items():
            if k not in self.diag:
                self._grow(self.diag, k, (), np.asarray(v).dtype if len(v) else np.float64)
            self._append(self.diag[k], v)
        self.h5.flush()

    def write_series(self, records: dict[str, list], names: tuple[str, ...]) -> None:
        """Append per-member records: ``names`` (the observables) to ``/observables/<name>``, the
        run's own series to ``/series/<key>``, each ``(records, members)``, and their ``time`` to both."""
        require_space(self.at, 8 * sum(np.size(v) for v in records.values()))
        for group, keys in (("series", [k for k in records if k not in names]), ("observables", ["time", *names])):
            if group == "observables" and not names:
                continue
            g = self.h5.require_group(group)
            for k in keys:
                v = np.asarray(records[k])
                if k not in g:
                    self._grow(g, k, v.shape[1:], v.dtype)
                self._append(g[k], v)
        self.h5.flush()

    def write_table(self, name: str, records: list[dict]) -> None:
        """``/name/<key>``: one dataset per key of equal-keyed records (the hybrid's regrid log)."""
        if records:
            require_space(self.at, 8 * len(records) * len(records[0]))
            g = self.h5.create_group(name)
            for k in records[0]:
                _label(g.create_dataset(k, data=np.array([r[k] for r in records])))
            self.h5.flush()

    def annotate(self, name: str, value) -> None:
        """Set the root attribute ``name`` (JSON text for a dict: ``timing``, ``chunks``)."""
        self.h5.attrs[name] = json.dumps(value) if isinstance(value, dict) else value
        self.h5.flush()

    def close(self, wall_time: float | None = None, error: str | None = None) -> None:
        """Close the file, marked complete only without ``error``; after an I/O error, as far as the
        file system still allows (it stays marked incomplete, as it was created)."""
        if not self.h5.id.valid:
            return
        try:
            if wall_time is not None:
                self.h5.attrs["wall_time"] = wall_time
            if error is not None:
                self.h5.attrs["error"] = error
            self.h5.attrs["complete"] = error is None
        finally:
            try:
                close_h5(self.h5)
            except OSError:
                if error is None:
                    raise


def _label(ds):
    """``ds`` with its ``units`` attribute (:func:`ti_dk.output.units.units_of`), where one is listed."""
    units = units_of(ds.name)
    if units is not None:
        ds.attrs["units"] = units
    return ds


def scene_json(scene) -> str:
    """The scene as stored in every file ti_dk writes (the ``scene`` attribute)."""
    return json.dumps(scene.to_dict())


def same_scene(h5, scene) -> bool:
    """Whether an HDF5 file was written for these scene settings, up to ``pool_layout`` (where the
    particles are stored changes no bit of a run, so either layout continues the other's files)."""
    ours, theirs = json.loads(scene_json(scene)), json.loads(h5.attrs["scene"])
    for d in (ours, theirs):
        d.get("hybrid", {}).pop("pool_layout", None)
    return ours == theirs


def write_group(f, name: str, table: dict) -> None:
    """One dataset per entry of ``table`` under ``name``."""
    for k, v in table.items():
        f.create_dataset(f"{name}/{k}", data=np.asarray(v))


def read_group(g) -> dict:
    """Every dataset of HDF5 group ``g``, read whole, by name."""
    return {k: g[k][()] for k in g}


def write_rows(f, rows: list[dict]) -> None:
    """Statistics rows (with their accumulators) as ``rows/<i>/<key>``."""
    for i, row in enumerate(rows):
        write_group(f, f"rows/{i}", row)


def read_rows(f) -> list[dict]:
    """The statistics rows :func:`write_rows` wrote to ``f`` (none: an empty list)."""
    return [read_group(f[f"rows/{i}"]) for i in range(len(f["rows"]))] if "rows" in f else []


@contextmanager
def atomic_h5(path: Path):
    """An HDF5 file written under a fresh temporary name (created exclusively, never through a link)
    and renamed once whole (``rename`` replaces a link at ``path`` rather than following it);
    removed if interrupted, so whatever carries ``path`` is always complete."""
    fd, name = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    os.fchmod(fd, 0o644)  # as an ordinary file (mkstemp makes it private)
    os.close(fd)
    tmp = Path(name)
    try:
        f = h5py.File(tmp, "w")
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    try:
        yield f
        close_h5(f)
    except BaseException:
        try:
            close_h5(f)
        except OSError:
            pass
        tmp.unlink(missing_ok=True)
        raise
    tmp.replace(path)


def close_h5(f) -> None:
    """Close an HDF5 file; a write failure while flushing (disk full) is an OSError, not h5py's
    RuntimeError, so that callers see every I/O failure as one kind of error."""
    try:
        f.close()
    except RuntimeError as exc:
        raise OSError(str(exc)) from None


def _b(text: str) -> np.bytes_:
    """openPMD string attributes as fixed-length bytes (what yt and openPMD-viewer expect)."""
    return np.bytes_(text.encode())


def pack_ids(pid: np.ndarray) -> np.ndarray:
    """openPMD particle ids: each ``(slot at birth, birth step + 1)`` u32 pair as one u64."""
    return (pid[:, 0].astype(np.uint64) << np.uint64(32)) | pid[:, 1].astype(np.uint64)


def write_openpmd(directory: Path, iteration: int, t: float, dt: float, grid, density: np.ndarray,
                  region: np.ndarray | None = None, positions: np.ndarray | None = None,
                  ids: np.ndarray | None = None, boxes: np.ndarray | None = None,
                  si: tuple[float, float] = (0.0, 0.0)) -> Path:
    """One openPMD 1.1.0 snapshot (file-based: ``data<iteration>.h5``) of one ensemble member.

    Meshes ``density`` (number density), ``negative_cells`` and, for the hybrid,
    ``particle_region`` (1 where covered); species ``particles`` with ``position`` and ``id``;
    the box list as ``/ti_dk/boxes`` (rows: lo..., hi... in cells), outside the base path.
    Written to a temporary name and renamed, so a snapshot on disk is always whole.

    Units: ``si`` = (L in metres, D in m²/s), the scene's ``length_si`` and ``diffusion_si``.
    Without L (0) lengths and densities are pure numbers in units of L (``unitDimension`` 0,
    ``unitSI`` 1); with it they are in metres (``unitSI`` L^p, ``unitDimension`` L^p); times are in
    seconds (``timeUnitSI`` L²/(2D)) only with D as well. The root attribute ``ti_dk_units`` says
    which, in words.
    """
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"data{iteration:06d}.h5"
    require_space(directory, 3 * density.nbytes + (0 if positions is None else 3 * positions.nbytes))
    with atomic_h5(path) as f:
        a = f.attrs
        a["openPMD"], a["openPMDextension"] = _b("1.1.0"), np.uint32(0)
        a["basePath"], a["meshesPath"], a["particlesPath"] = _b("/data/%T/"), _b("meshes/"), _b("particles/")
        a["iterationEncoding"], a["iterationFormat"] = _b("fileBased"), _b("data%06T.h5")
        a["software"], a["softwareVersion"] = _b("ti_dk"), _b(package_version())
        a["date"] = _b(time.strftime("%Y-%m-%d %H:%M:%S %z"))
        length, diffusion = si
        tau = length**2 / (2 * diffusion) if length and diffusion else 0.0  # the time unit L²/(2D) [s]
        lengths = f"lengths in L = {length:g} m" if length else \
            "lengths in units of the scene's L, pure numbers (unitSI 1, unitDimension 0; length_si gives metres)"
        times = (f"times in L^2/(2D) = {tau:g} s" if tau else "times in units of L^2/(2D), not seconds "
                 "(timeUnitSI 1 stands for that unit; length_si and diffusion_si give seconds)")
        a["ti_dk_units"] = _b(f"{lengths}; {times}")
        it = f.create_group(f"data/{iteration}")
        it.attrs["time"], it.attrs["dt"], it.attrs["timeUnitSI"] = float(t), float(dt), tau or 1.0
        _openpmd_meshes(it.create_group("meshes"), grid, density, region, length)
        if positions is not None:
            _openpmd_particles(it.create_group("particles/particles"), positions, ids, length)
        if boxes is not None:
            f.create_dataset("ti_dk/boxes", data=boxes)
            f["ti_dk"].attrs["columns"] = _b("lo (one per axis), hi (one per axis), in cells; hi exclusive")
    return path


def _unit(power: int, length: float) -> dict:
    """``unitSI`` and ``unitDimension`` of a quantity of dimension L^power: in metres with ``length``
    (L in metres), else a pure number in units of L."""
    return {"unitSI": float(length**power) if length else 1.0,
            "unitDimension": np.array([power if length else 0, 0, 0, 0, 0, 0, 0], dtype=np.float64)}


def _openpmd_meshes(meshes, grid, density: np.ndarray, region: np.ndarray | None, length: float) -> None:
    """Meshes ``density``, ``negative_cells`` and, with a region, ``particle_region``."""
    d = grid.dim
    labels = [_b(a) for a in "xyz"[:d]]
    fields = {"density": (density, -d), "negative_cells": ((density < 0).astype(np.uint8), 0)}
    if region is not None:
        fields["particle_region"] = (region.astype(np.uint8), 0)
    for name, (data, length_power) in fields.items():
        ds = meshes.create_dataset(name, data=data)
        ds.attrs.update(_unit(length_power, length))
        ds.attrs["timeOffset"] = np.float32(0.0)
        ds.attrs["geometry"], ds.attrs["dataOrder"] = _b("cartesian"), _b("C")
        ds.attrs["axisLabels"] = np.array(labels)
        ds.attrs["gridSpacing"] = np.array(grid.dx, dtype=np.float64)
        ds.attrs["gridGlobalOffset"] = np.zeros(d)
        ds.attrs["gridUnitSI"] = _unit(1, length)["unitSI"]
        ds.attrs["position"] = np.full(d, 0.5)


def _openpmd_particles(sp, positions: np.ndarray, ids: np.ndarray, length: float) -> None:
    """Species records ``position``, ``positionOffset`` (constant 0) and ``id``."""
    n, d = positions.shape
    for rec, power in (("position", 1), ("positionOffset", 1), ("id", 0)):
        g = sp.create_group(rec) if rec != "id" else None
        if rec == "id":
            g = sp.create_dataset("id", data=np.asarray(ids, dtype=np.uint64))
            g.attrs["unitSI"] = 1.0
        else:
            for k, axis in enumerate("xyz"[:d]):
                if rec == "position":
                    c = g.create_dataset(axis, data=np.asarray(positions[:, k], dtype=np.float64))
                else:
                    c = g.create_group(axis)
                    c.attrs["value"], c.attrs["shape"] = 0.0, np.array([n], dtype=np.uint64)
                c.attrs["unitSI"] = _unit(power, length)["unitSI"]
        g.attrs["unitDimension"] = _unit(power, length)["unitDimension"]
        g.attrs["timeOffset"] = np.float32(0.0)
