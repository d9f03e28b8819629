"""HDF5 record of a run: statistics rows, per-step diagnostics and provenance."""
from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import h5py
import numpy as np

STAT_KEYS = ("mean", "variance", "skewness", "kurtosis")


def versions() -> dict[str, str]:
    import taichi

    from . import __version__

    return {"ti_dk": __version__, "taichi": ".".join(map(str, taichi.__version__)), "numpy": np.__version__,
            "h5py": h5py.__version__, "python": platform.python_version()}


class RunFile:
    """One run's HDF5 file.

    Layout: attributes ``scene`` (JSON), ``versions`` (JSON), ``seed``, ``complete``,
    ``wall_time``; ``/stats/time`` and ``/stats/{mean,variance,skewness,kurtosis}`` shaped
    ``(n_rows, *cells)`` in number-density units, ``/stats/n_samples``, optional
    ``/stats/histogram`` ``(n_rows, *cells, bins)`` with attribute ``lo``; ``/diagnostics/*`` one
    entry per step; ``/regrid/*`` one entry per regrid of a hybrid run. Every row is flushed when written; ``complete`` turns true only at the end, so
    a killed run leaves a readable file that says it is unfinished.
    """

    def __init__(self, path: Path, scene, histogram_bins: int | None = None):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.h5 = h5py.File(path, "w")
        self.path = path
        a = self.h5.attrs
        a["scene"] = json.dumps(scene.to_dict())
        a["versions"] = json.dumps(versions())
        a["seed"] = np.uint64(scene.seed)
        a["created"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        a["complete"] = False
        st = self.h5.create_group("stats")
        st.attrs["units"] = "number density (particles per unit volume)"
        st.attrs["cell_volume"] = scene.cell_volume
        self._grow(st, "time", (), np.float64)
        self._grow(st, "n_samples", (), np.int64)
        for k in STAT_KEYS:
            self._grow(st, k, scene.cells, np.float64)
        if histogram_bins:
            self._grow(st, "histogram", (*scene.cells, histogram_bins), np.int64).attrs["lo"] = scene.histogram[0]
            self._grow(st, "histogram_outside", scene.cells, np.int64)
        self.diag = self.h5.create_group("diagnostics")
        self.h5.flush()

    @staticmethod
    def _grow(group, name, shape, dtype):
        return group.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                                    chunks=(1, *shape) if shape else (1024,))

    @staticmethod
    def _append(ds, rows) -> None:
        rows = np.asarray(rows)
        n = ds.shape[0]
        ds.resize(n + rows.shape[0], axis=0)
        ds[n:] = rows

    def write_row(self, t: float, row: dict[str, np.ndarray]) -> None:
        st = self.h5["stats"]
        self._append(st["time"], [t])
        for k, v in row.items():
            self._append(st[k], np.asarray(v)[None])
        self.h5.flush()

    def write_diagnostics(self, diag: dict[str, list]) -> None:
        for k, v in diag.items():
            if k not in self.diag:
                self._grow(self.diag, k, (), np.asarray(v).dtype if len(v) else np.float64)
            self._append(self.diag[k], v)
        self.h5.flush()

    def write_table(self, name: str, records: list[dict]) -> None:
        """``/name/<key>``: one dataset per key of equal-keyed records (the hybrid's regrid log)."""
        if records:
            g = self.h5.create_group(name)
            for k in records[0]:
                g.create_dataset(k, data=np.array([r[k] for r in records]))
            self.h5.flush()

    def close(self, wall_time: float | None = None, error: str | None = None) -> None:
        if wall_time is not None:
            self.h5.attrs["wall_time"] = wall_time
        if error is not None:
            self.h5.attrs["error"] = error
        self.h5.attrs["complete"] = error is None
        self.h5.close()
