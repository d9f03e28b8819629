"""A study's runs: each scene run once through :func:`ti_dk.run` into its HDF5 file, then read back.

A complete file written for exactly the same scene is read instead of running again, so a figure
can be redrawn (or a table rebuilt) without repeating its simulations.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

import ti_dk
from ti_dk.output import claim, files
from ti_dk.scene import load
from ti_dk.control.runtime import Stats


@dataclass(frozen=True)
class Run:
    """One run as its HDF5 file records it (layout: :class:`ti_dk.output.files.RunFile`)."""

    scene: ti_dk.Scene
    path: Path
    times: np.ndarray  # /stats/time: the output times of the rows
    stats: Stats  # /stats/*: per row and cell, in number density (particles per unit volume)
    diagnostics: dict[str, np.ndarray] = field(repr=False)  # /diagnostics/*: one entry per step
    wall_time: float = 0.0  # seconds the run took (attribute wall_time)

    @property
    def cell_volume(self) -> float:
        return self.scene.grid.cell_volume


def read_run(path: Path, scene: ti_dk.Scene) -> Run:
    """The run of ``scene`` recorded in ``path``. A one-member file holds only the mean (that
    member's density); its other moments read as NaN."""
    with h5py.File(path, "r") as f:
        st = files.read_group(f["stats"])
        lo = f["stats/histogram"].attrs["lo"] if "histogram" in f["stats"] else None
        diagnostics = files.read_group(f["diagnostics"])
        wall = float(f.attrs["wall_time"])
    nan = np.full_like(st["mean"], np.nan)
    stats = Stats(mean=st["mean"], variance=st.get("variance", nan), skewness=st.get("skewness", nan),
                  kurtosis=st.get("kurtosis", nan), n_samples=st["n_samples"], histogram=st.get("histogram"),
                  hist_lo=None if lo is None else int(lo))
    return Run(scene=scene, path=path, times=st["time"], stats=stats, diagnostics=diagnostics, wall_time=wall)


def recorded(path: Path, scene: ti_dk.Scene) -> bool:
    """Whether ``path`` is a complete run file written for exactly ``scene``."""
    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("complete", False)) and files.same_scene(f, scene)
    except (OSError, KeyError, json.JSONDecodeError):
        return False


@dataclass(frozen=True)
class Runs:
    """Where a study keeps its runs, and the scene keys it applies to every one of them.

    ``get(tag, name, **keys)`` loads scene ``name`` with ``keys`` (then ``overrides``, which win),
    and returns its run from ``root/tag/<scene>_<method>.h5``, running it first unless that file
    already records this very scene (``rerun``: always run).
    """

    root: Path
    overrides: dict = field(default_factory=dict)  # --set KEY=VALUE of the command line
    rerun: bool = False
    progress: bool = False

    def scene(self, name: str, **keys) -> ti_dk.Scene:
        return ti_dk.load_scene(name, **keys | self.overrides)

    def get(self, tag: str, name: str, **keys) -> Run:
        scene = self.scene(name, **keys)
        out = self.root / tag
        path = claim.Outputs.of(out, scene).run_file
        if self.rerun or not recorded(path, scene):  # a stale or unwanted file is replaced
            ti_dk.run(scene, out=out, progress=self.progress, frames=False, snapshots=False, overwrite=True)
        return read_run(path, scene)


def parse_sets(items: list[str]) -> dict:
    """``--set KEY=VALUE`` items as scene overrides (values parsed as TOML, as by ti_dk.scene)."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ti_dk.ConfigError(f"--set {item!r}: write KEY=VALUE, e.g. --set cells=[20]")
        out[key.strip()] = load.parse_value(value.strip())
    return out
