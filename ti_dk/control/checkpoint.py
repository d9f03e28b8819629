"""Checkpoints: everything a run needs to resume bit for bit, written atomically and checked whole
before anything of it is loaded."""
from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..core.errors import ConfigError
from ..scene.schema import Scene
from ..output.files import (atomic_h5, package_version, read_group, read_rows, require_space, same_scene, scene_json,
                            write_group, write_rows)
from ..methods.solver import Solver


@dataclass
class Progress:
    """What a run has produced so far: enough, with the solver states, to resume it exactly."""

    step: int = 0  # steps done
    rows: list = field(default_factory=list)  # statistics rows (dicts of arrays)
    times: list = field(default_factory=list)  # their times
    diag: dict = field(default_factory=lambda: {"time": []})  # per step: every key the solvers report
    frames: dict = field(default_factory=lambda: {"time": [], "negative_cells": []})  # per frame
    series: dict = field(default_factory=dict)  # per record: time and per-member series (handlers.Observations)
    pooled: dict | None = None  # stationary runs: the pooled accumulator's state
    timing: dict = field(default_factory=dict)  # seconds per part of the run
    wall: float = 0.0  # seconds the run had taken when the checkpoint was written


FORMAT = 2  # the checkpoint layout; a file of a newer one is refused (1: no version, no digest)


def write_checkpoint(path: Path, scene: Scene, solver: Solver, other: Solver | None, prog: Progress) -> None:
    """Everything needed to resume at ``prog.step``; written to a temporary name, then renamed."""
    states = {name: s.state() for name, s in (("solver", solver), ("compare", other)) if s is not None}
    require_space(path, sum(v.nbytes for st in states.values() for v in st.values()))
    with atomic_h5(path) as f:  # interrupted (SIGTERM): the previous checkpoint stays the latest
        f.attrs["format"], f.attrs["ti_dk"] = FORMAT, package_version()
        f.attrs["scene"] = scene_json(scene)
        f.attrs["step"], f.attrs["wall"] = prog.step, prog.wall
        f.attrs["timing"] = json.dumps(prog.timing | ({"hybrid": dict(solver.timing)} if solver.timing else {}))
        for name, st in states.items():
            write_group(f, name, st)
        f.create_dataset("times", data=np.array(prog.times, dtype=np.float64))
        write_rows(f, prog.rows)
        write_group(f, "diag", prog.diag)
        write_group(f, "frames", prog.frames)
        write_group(f, "series", prog.series)
        write_group(f, "pooled", prog.pooled or {})
        f.attrs["digest"] = content_digest(f)


def content_digest(f) -> str:
    """SHA-256 over every attribute (but ``digest``) and every dataset's name, type, shape and bytes:
    a member's or a cell's values moved, even with the mass unchanged, change it."""
    h = hashlib.sha256()
    for k in sorted(f.attrs):
        if k != "digest":
            h.update(f"{k}={f.attrs[k]!r};".encode())
    names: list[str] = []
    f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
    for name in sorted(names):
        v = np.ascontiguousarray(f[name][()])
        h.update(f"{name}:{v.dtype.str}:{v.shape};".encode())
        h.update(v.tobytes())
    return h.hexdigest()


def _release(version: str) -> tuple[int, ...]:
    """``"1.2.3rc1"`` as ``(1, 2, 3)``, to compare releases; ``()`` when it names none."""
    return tuple(int(p) for p in re.findall(r"\d+", version.split("+")[0])[:3])


def check_checkpoint_file(path: Path, scene: Scene) -> None:
    """Refuse, before the run claims its output, a file that is not a checkpoint, one of a newer
    format or ti_dk, one whose content differs from its digest, or one of other scene settings
    (naming each setting that differs, with both values)."""
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ConfigError(f"--restart {path}: not a readable checkpoint ({str(exc).splitlines()[0]}); give a file "
                          "written by --checkpoint-every") from None
    with f:
        a = f.attrs
        if "scene" not in a or "step" not in a:
            raise ConfigError(f"--restart {path}: not a ti_dk checkpoint; give a file written by --checkpoint-every")
        try:
            fmt, by = int(a.get("format", 1)), str(a.get("ti_dk", "unknown"))
            if fmt > FORMAT or _release(by) > _release(package_version()) > ():
                raise ConfigError(f"--restart {path}: written by ti_dk {by} (checkpoint format {fmt}), newer than this "
                                  f"ti_dk {package_version()} (format {FORMAT}); restart with that version or from the start")
            if fmt < FORMAT or "digest" not in a:
                raise ConfigError(f"--restart {path}: an old checkpoint without a content digest (format {fmt}); "
                                  "restart from the start")
            if not same_scene(f, scene):
                raise ConfigError(f"--restart {path}: the checkpoint was written for other settings ("
                                  + scene_difference(json.loads(a["scene"]), json.loads(scene_json(scene)))
                                  + "); restart with its settings")
            if content_digest(f) != str(a["digest"]):
                raise ConfigError(f"--restart {path}: damaged checkpoint (its content differs from its digest); "
                                  "restart from another checkpoint or from the start")
        except (KeyError, ValueError, TypeError, OSError, RecursionError, AttributeError) as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError(f"--restart {path}: damaged checkpoint ({type(exc).__name__}); restart from another "
                              "checkpoint or from the start") from None


def scene_difference(theirs: dict, ours: dict, prefix: str = "") -> str:
    """Each setting that differs between two scenes' dicts, as ``key: checkpoint X, now Y``."""
    out = []
    for k in sorted(set(theirs) | set(ours)):
        a, b = theirs.get(k, "absent"), ours.get(k, "absent")
        if k == "pool_layout" or a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += [scene_difference(a, b, f"{prefix}{k}.")] if scene_difference(a, b) else []
        else:
            out.append(f"{prefix}{k}: checkpoint {json.dumps(a)}, now {json.dumps(b)}")
    return "; ".join(out)


def read_checkpoint(path: Path, scene: Scene, solver: Solver, other: Solver | None) -> Progress:
    """The progress a checkpoint holds, loaded into the solvers after :func:`checkpoint_problem`
    found nothing wrong with it; anything else is refused with one line."""
    damaged = f"--restart {path}: damaged checkpoint"
    check_checkpoint_file(path, scene)
    with h5py.File(path, "r") as f:
        try:
            states = {name: read_group(f[name]) for name in ("solver", "compare") if name in f}
            timing = json.loads(f.attrs["timing"])
            prog = Progress(step=int(f.attrs["step"]), times=list(f["times"][()]), timing=timing, rows=read_rows(f),
                             diag={k: list(v) for k, v in read_group(f["diag"]).items()},
                             frames={k: list(v) for k, v in read_group(f["frames"]).items()},
                             series={k: list(v) for k, v in read_group(f["series"]).items()} if "series" in f else {},
                             pooled=read_group(f["pooled"]) or None if "pooled" in f else None,
                             wall=float(f.attrs.get("wall", 0.0)))
        except (KeyError, ValueError, TypeError, OSError) as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError(f"{damaged} ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); "
                              "restart from another checkpoint or from the start") from None
    try:
        problem = checkpoint_problem(scene, prog, states, {"solver": solver, "compare": other})
    except (KeyError, IndexError, ValueError) as exc:  # a table missing or cut short
        problem = f"{type(exc).__name__} {exc}"
    if problem:
        raise ConfigError(f"{damaged}: {problem}; restart from another checkpoint or from the start")
    solver.load_state(states["solver"])
    if other is not None:
        other.load_state(states["compare"])
    if "hybrid" in prog.timing:
        solver.timing = prog.timing.pop("hybrid")
    return prog


_VARIABLE = ("x", "pid", "boxes")  # hybrid state whose length changes with the particles (and regrid_*)


def checkpoint_problem(scene: Scene, prog: Progress, states: dict, solvers: dict) -> str | None:
    """What is wrong with a checkpoint's content, or None: step and row counts, the state's keys,
    shapes and types (against a fresh solver's), finite values, particles inside the domain and,
    for the hybrid, in their region, and the mass the state holds against the diagnostics."""
    step, n = prog.step, scene.n_steps
    missing = {"time", "mass"} - set(prog.diag)
    if missing:
        return f"its diagnostics lack {', '.join(sorted(missing))}"
    if not 0 < step < n:
        return f"step {step} is outside 1 … {n - 1}"
    if any(len(v) != step for v in prog.diag.values()) or not math.isclose(prog.diag["time"][-1], step * scene.dt,
                                                                           rel_tol=1e-9):
        return f"its per-step diagnostics do not end at step {step}"
    records = step // scene.observe_every + 1  # handlers.Observations: step 0 and every observe_every-th
    if any(len(v) != records for v in prog.series.values()) or not {"time", "mass", *(
            name for name, _ in scene.stats.observables)} <= set(prog.series):
        return f"its per-member series do not hold the {records} records of step {step}"
    rows = 0 if scene.stats.t_equil is not None else sum(1 for s in scene.output_steps if s <= step)
    if len(prog.rows) != rows or len(prog.times) != rows:
        return f"it holds {len(prog.rows)} statistics rows where step {step} has {rows}"
    for name, solver in solvers.items():
        if solver is None:
            continue
        if name not in states:
            return f"the {name} state is missing"
        st, fresh = states[name], solver.state()
        if set(st) != set(fresh):
            return f"the {name} state has keys {sorted(st)}, not {sorted(fresh)}"
        for k, v in st.items():
            variable = k in _VARIABLE or k.startswith("regrid_")
            if v.dtype != fresh[k].dtype or (v.shape != fresh[k].shape if not variable else v.ndim != fresh[k].ndim):
                return f"{name}/{k} has shape {v.shape} {v.dtype}, not {fresh[k].shape} {fresh[k].dtype}"
            if v.dtype.kind == "f" and not k.startswith("regrid_") and not np.isfinite(v).all():
                return f"{name}/{k} holds NaN or infinite values"
        problem = state_problem(scene, name, st, solver, prog.diag)
        if problem:
            return problem
    return None


def state_problem(scene: Scene, name: str, st: dict, solver: Solver, diag: dict) -> str | None:
    """Particles inside the domain (and the hybrid's region), and the mass against the diagnostics."""
    vol, lengths = scene.grid.cell_volume, np.array(scene.grid.lengths)
    counts = st.get("n_alive", st.get("n_real"))
    if counts is not None:
        x = st["x"]
        if counts.shape != (scene.method.ensemble,) or counts.min() < 0 or counts.max() > x.shape[-2]:
            return f"{name}: particle counts {counts.tolist()[:4]} do not fit its {x.shape[-2]} slots"
        live = np.arange(x.shape[-2])[None, :] < counts[:, None]
        pos = x[live]
        if pos.size and ((pos < 0).any() or (pos >= lengths).any()):
            return f"{name}: particles lie outside the domain [0, {list(scene.grid.lengths)})"
    prefix = "" if name == "solver" else "compare_"
    if "n_alive" in st:
        mass = float(counts.sum())
    else:
        q = st["spde_q" if "spde_q" in st else "q"]
        mass = float(q.astype(np.float64).sum() * vol)
    if "n_real" in st:  # hybrid: covered cells hold exactly their particles, and the boxes cover the region
        cells = np.minimum((pos / np.array(scene.grid.dx)).astype(np.int64), np.array(scene.grid.cells) - 1)
        member = np.nonzero(live)[0]
        covered = st["covered"].astype(bool)
        if pos.size and not covered[(member, *cells.T)].all():
            return f"{name}: particles lie outside the particle region"
        count = np.zeros(covered.shape)
        np.add.at(count, (member, *cells.T), 1)
        if not np.allclose((st["spde_q"] * vol)[covered], count[covered], rtol=1e-6, atol=1e-6):
            return f"{name}: the densities of the particle region differ from its particle counts"
        region = np.zeros_like(covered)
        for e, *b in st["boxes"]:
            d = scene.grid.dim
            region[(e, *(slice(lo, hi) for lo, hi in zip(b[:d], b[d:])))] = True
        if not np.array_equal(region, covered):
            return f"{name}: the particle region differs from its boxes"
    want = float(diag[prefix + "mass"][-1])
    tol = 1e-5 if scene.method.precision == "f32" else 1e-9
    if not math.isclose(mass, want, rel_tol=tol, abs_tol=tol):
        return f"{name}: its state holds {mass:.10g} particles where the diagnostics say {want:.10g}"
    return None
