"""Scene parameters: frozen dataclasses, TOML loading, and the one place input is validated.

A scene file groups its keys in tables (``[grid]``, ``[init]``, ``[time]``, ``[method]``,
``[hybrid]``, ``[stats]``, ``[output]``); the loaded :class:`Scene` holds one frozen section per
table (``scene.grid.cells``, ``scene.method.name``, ``scene.hybrid.threshold``). Every key name is
unique across tables, so every key can also be given flat: at the top of a file, or overridden by
its bare name (``load_scene("void1d", ppc=5, C=0.05)`` or ``--set ppc=5``). Densities in scene
files are in particles per cell; inside the solvers they are number densities (particles per unit
volume).

Every key is declared once, as a section field carrying a :class:`Key` (kind, limits or
choices, a one-line doc); validation, ``--set`` parsing and ``--help`` all read that declaration.
The run options that are not scene keys (``--out``, Dask sizes, checkpoints) are checked by
:func:`check_options`, and what a scene needs (memory, steps, time) by :func:`memory_estimate`
and :func:`work_estimate`, all before Taichi starts.
"""
from __future__ import annotations

import os

# Taichi prints a "[Taichi] version ..." banner when imported unless this is false; config is the
# first module of ti_dk to load (grid imports taichi), so the banner is off for every entry point.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")

import dataclasses  # noqa: E402
import inspect  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import warnings  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

import numpy as np  # noqa: E402

from . import initial  # noqa: E402
from .grid import Geometry, Grid  # noqa: E402
from .pool import LAYOUTS as POOL_LAYOUTS  # noqa: E402
from .pool import capacity  # noqa: E402
from .regrid import RegridParams  # noqa: E402
from .rng import PURPOSE_BITS  # noqa: E402

SCENE_DIR = Path(__file__).resolve().parent.parent / "scenes"
METHODS = ("fv", "gaussian", "particle", "hybrid")
SPDES = ("fv", "gaussian")  # the SPDE a hybrid run keeps on the whole grid
GHOST_PROFILES = ("mean", "linear", "uniform")  # how sampled particles lie in their cell (see HybridSolver)
BOUNDARY_KINDS = ("periodic", "neumann", "dirichlet")
PRECISIONS = ("f32", "f64")
PARTICLE_INITS = ("per_cell", "exact_uniform")
ID_BITS_MIN = 8  # hybrid particle ids: birth cell in the high bits, at least this many for the index in the cell
# hybrid: particle steps a run may take. A particle's birth word (birth step + 1, or'd with this
# flag for particles sampled at a regrid: ghosts.REGRID_BIRTH) is shifted left by rng.PURPOSE_BITS
# into one 32-bit counter word (particles.Walker.bits), so birth steps live in 27 bits
HYBRID_STEP_LIMIT = 1 << (32 - PURPOSE_BITS - 1)
CLAMP_WARN = 1e-3  # warn when a particle step is clamped with more than this probability
MAX_STEPS = 2**32 - 1  # the step is one 32-bit word of every random-number counter (rng.py)
MAX_MEMBERS = 2**32  # so is the member index
MAX_FIELD = 2**31 - 1  # Taichi indexes a field with 32-bit integers: members x cells must fit
MAX_PPC = 1e15  # particles per cell: beyond, counts are not exact in f64 and fourth moments overflow
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")  # a scene name is a plain file name
_RG = RegridParams()  # the clustering defaults, written once in regrid.py


class ConfigError(ValueError):
    """Bad scene input; the message says what to change."""


class ClampWarning(UserWarning):
    """The time step makes clamped particle steps (|step| > Δx) more likely than 1e-3."""


@dataclass(frozen=True)
class Key:
    """One scene key: what kind of value it takes, its limits or choices, and a one-line doc.

    ``kind``: ``real``, ``int``, ``choice``, ``bool`` or ``text`` (checked by :meth:`check`), or
    ``special`` (a list or pair with its own reader in :func:`make_scene`; ``form`` says what).
    """

    kind: str
    doc: str
    lo: float | None = None  # smallest value allowed
    hi: float | None = None  # largest value allowed
    above: bool = False  # lo itself is not allowed
    choices: tuple = ()
    form: str = ""  # what a special key takes, for --help

    def describe(self) -> str:
        """What the key takes, e.g. 'a number > 0' or 'one of fv, gaussian'."""
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        if self.kind == "bool":
            return "true or false"
        if self.kind in ("text", "special"):
            return self.form or "text"
        what = "a whole number" if self.kind == "int" else "a number"
        fmt = (lambda v: str(int(v))) if self.kind == "int" else (lambda v: f"{v:g}")
        if self.lo is not None and self.hi is not None:
            return f"{what} in {'(' if self.above else '['}{fmt(self.lo)}, {fmt(self.hi)}]"
        if self.lo is not None:
            return f"{what} {'>' if self.above else '>='} {fmt(self.lo)}"
        return "a finite number" if self.kind == "real" else what

    def check(self, name: str, value: Any) -> Any:
        """The value, typed; a one-line :class:`ConfigError` naming ``name`` when it does not fit."""
        if self.kind == "choice":
            if value not in self.choices:
                raise ConfigError(f"{name} = {value!r}: use {self.describe()}")
            return value
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise ConfigError(f"{name} = {value!r}: give true or false")
            return value
        if self.kind == "text":
            if not isinstance(value, str):
                raise ConfigError(f"{name} = {value!r}: give a text in quotes")
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                self.kind == "int" and not isinstance(value, int)):
            raise ConfigError(f"{name} = {value!r}: give {'a whole number' if self.kind == 'int' else 'a number'}")
        if self.kind == "real":
            value = float(value)
        below = self.lo is not None and (value < self.lo or (self.above and value == self.lo))
        if not math.isfinite(value) or below or (self.hi is not None and value > self.hi):
            raise ConfigError(f"{name} = {value!r}: give {self.describe()}")
        return value


def key(kind: str, doc: str, default: Any = dataclasses.MISSING, flat: str | None = None, **limits) -> Any:
    """A scene section's field declared with its :class:`Key`; ``flat``: its name in flat form
    (``--set``, top-level TOML) when that differs from the field's."""
    return dataclasses.field(default=default, metadata={"key": Key(kind, doc, **limits), "flat": flat})


@dataclass(frozen=True)
class GridKeys(Geometry):
    """``[grid]``: the uniform Cartesian grid on ``[0, L_0] × … × [0, L_{d-1}]`` (paper §2.2.1)."""

    cells: tuple[int, ...] = key("special", "cells per axis; the number of entries is the dimension",
                                 form="1 to 3 whole numbers >= 2, e.g. [64, 64]")
    lengths: tuple[float, ...] = key("special", "domain length per axis (default 1 each)",
                                     form="one number > 0 per axis")
    boundary: tuple[tuple[str, str], ...] = key(
        "special", "boundary of each side (default periodic)",
        form=f"one of {', '.join(BOUNDARY_KINDS)}; per axis, or [lo, hi] per axis")
    reservoir_ppc: tuple[tuple[float, float], ...] = key(
        "special", "dirichlet sides: reservoir density in particles per cell (default 0)",
        form=f"a number in [0, {MAX_PPC:g}]; per axis, or [lo, hi] per axis")


@dataclass(frozen=True)
class InitKeys:
    """``[init]``: the initial condition (a function of :mod:`ti_dk.initial`) and its own keys."""

    name: str = key("special", "the initial condition ([init] name = ...)", flat="init",
                    form="one of " + ", ".join(initial.REGISTRY))
    items: tuple[tuple[str, Any], ...] = ()  # its parameters (INIT_KEYS), sorted by name

    @property
    def params(self) -> dict[str, Any]:
        return dict(self.items)


@dataclass(frozen=True)
class TimeKeys:
    """``[time]``: explicit steps ``Δt = C · min(Δx_a)²`` up to ``t_end``."""

    C: float = key("real", "time step dt = C min(dx)^2", 0.0625, lo=0.0, above=True)
    t_end: float = key("real", "end time", 0.01, lo=0.0, above=True)
    allow_unstable: bool = key("bool", "accept C beyond the explicit stability limit (experiments)", False)


@dataclass(frozen=True)
class MethodKeys:
    """``[method]``: what advances the density, for how many members, from which seed."""

    name: str = key("choice", "what advances the density ([method] name = ...)", "fv", flat="method", choices=METHODS)
    ensemble: int = key("int", "independent members", 1, lo=1, hi=MAX_MEMBERS)
    seed: int = key("int", "random seed: the same seed gives the same bits on any thread count", 0,
                    lo=0, hi=2**64 - 1)
    precision: str = key("choice", "floating-point precision of the solvers", "f64", choices=PRECISIONS)
    particle_init: str = key("choice", "particle method: ppc per cell, or exactly ppc x cells uniform particles",
                             "per_cell", choices=PARTICLE_INITS)
    compare: str | None = key("special", "a second method run on the same start and drawn beside (default none)",
                              None, form="one of " + ", ".join(METHODS) + ", none")


@dataclass(frozen=True)
class HybridKeys:
    """``[hybrid]``: the SPDE kept everywhere, the particle region and how it meets the SPDE (§3)."""

    spde: str = key("choice", "the SPDE kept on the whole grid", "fv", choices=SPDES)
    threshold: float = key("real", "particles where the SPDE holds fewer particles per cell than this",
                           _RG.threshold, lo=0.0, above=True)
    ghost_profile: str = key("choice", "how sampled particles lie in their cell (mean: slope of q-bar)",
                             "mean", choices=GHOST_PROFILES)
    particle_substeps: int = key("int", "particle steps of dt/k per SPDE step (paper, end of 3.1)", 1,
                                 lo=1, hi=64)
    regrid_interval: int = key("int", "steps between regrids (0: the region is fixed)", 10, lo=0)
    buffer: int = key("int", "grow tagged cells by this many cells", _RG.buffer, lo=0)
    grid_efficiency: float = key("real", "smallest tagged fraction of a box", _RG.efficiency,
                                 lo=0.0, hi=1.0, above=True)
    min_box: int = key("int", "smallest box side in cells", _RG.min_box, lo=1)
    max_box: int = key("int", "largest box side in cells", _RG.max_box, lo=1)
    regrid_floor: float = key("real", "an uncovered cell below this times threshold before a step: cover all "
                              "below threshold (0: scheduled regrids only)", _RG.floor, lo=0.0, hi=1.0)
    pool_layout: str = key("choice", "particle storage: flat (slots per member) or pointer (blocks of cells, "
                           "only where the region is)", "flat", choices=POOL_LAYOUTS)

    @property
    def regrid(self) -> RegridParams:
        return RegridParams(threshold=self.threshold, buffer=self.buffer, efficiency=self.grid_efficiency,
                            min_box=self.min_box, max_box=self.max_box, floor=self.regrid_floor)


@dataclass(frozen=True)
class StatsKeys:
    """``[stats]``: when the ensemble's statistics are taken (rows at ``output_times``, or one
    pooled row for a stationary run, ``t_equil`` set)."""

    output_times: tuple[float, ...] = key("special", "times of the statistics rows and frames (t_end is always one)",
                                          (), form="a list of numbers in [0, t_end]")
    t_equil: float | None = key("special", "stationary runs: pool samples after this time (default: not stationary)",
                                None, form="a number in [0, t_end)")
    sample_every: int = key("int", "stationary runs: pool every k-th step", 1, lo=1)
    histogram: tuple[int, int] | None = key("special", "per-cell histogram of particles per cell, one-particle bins",
                                            None, form="[lo, hi], whole numbers with lo < hi")


@dataclass(frozen=True)
class OutputKeys:
    """``[output]``: what the run draws beyond its statistics."""

    movie_frames: int = key("int", "--movie: frames evenly spaced in time", 48, lo=1, hi=10_000)


SECTIONS = {"grid": GridKeys, "init": InitKeys, "time": TimeKeys, "method": MethodKeys, "hybrid": HybridKeys,
            "stats": StatsKeys, "output": OutputKeys}  # the scene file's tables, in their order


@dataclass(frozen=True)
class Scene:
    """A validated, immutable description of one run: a name and one section per scene-file table.

    Output rows are taken at the steps nearest to ``stats.output_times``; with ``stats.t_equil``
    set, the run is stationary and every ``sample_every``-th step after ``t_equil`` is pooled into
    one statistics row at ``t_end``.
    """

    grid: GridKeys
    init: InitKeys
    time: TimeKeys = TimeKeys()
    method: MethodKeys = MethodKeys()
    hybrid: HybridKeys = HybridKeys()
    stats: StatsKeys = StatsKeys()
    output: OutputKeys = OutputKeys()
    name: str = key("text", "the run's name; files are OUT/<name>_<method>.* (default: the scene file's name)",
                    "", form="a plain file name: letters, digits, '.', '_', '-'")
    description: str = key("text", "a line saying what the scene is", "")

    # -- derived time stepping ----------------------------------------------------------
    @property
    def dt(self) -> float:
        return self.time.C * min(self.grid.dx) ** 2

    @property
    def n_steps(self) -> int:
        return max(1, round(self.time.t_end / self.dt))

    @property
    def output_steps(self) -> tuple[int, ...]:
        if self.stats.t_equil is not None:
            return (self.n_steps,)
        return tuple(sorted({min(self.n_steps, round(t / self.dt)) for t in self.stats.output_times}))

    @property
    def stability_number(self) -> float:
        """``Σ_a Δt/Δx_a²``: the explicit FV scheme is stable for values below 1."""
        return sum(self.dt / h**2 for h in self.grid.dx)

    @property
    def clamp_probability(self) -> float:
        """Probability that one particle step (Δt / particle_substeps in the hybrid) along the finest axis
        exceeds Δx (and is clamped)."""
        substeps = self.hybrid.particle_substeps if self.method.name == "hybrid" else 1
        return math.erfc(min(self.grid.dx) / math.sqrt(2 * self.dt / substeps))

    @property
    def initial_ppc(self) -> np.ndarray:
        """The initial condition on the cell centres, in particles per cell."""
        return initial.density_ppc(self.init.name, self.init.params, self.grid.cells, self.grid.lengths)

    def to_dict(self) -> dict[str, Any]:
        """The scene as nested tables, as a scene file writes it."""
        d = dataclasses.asdict(self)
        d["init"] = {"name": self.init.name, **self.init.params}
        return d

    def flat(self) -> dict[str, Any]:
        """Every key by its flat name (the form ``--set`` and :func:`load_scene` overrides take)."""
        out = {"name": self.name, "description": self.description, **self.init.params}
        for sec, field_ in _WHERE.values():
            if sec is not None:
                out[_flat_name(field_)] = getattr(getattr(self, sec), field_.name)
        return out

    def replace(self, **flat: Any) -> "Scene":
        """This scene with some keys changed by flat name, the initial condition's own parameters
        included (no new validation: for values already valid; :func:`load_scene` validates)."""
        top = {k: flat.pop(k) for k in ("name", "description") if k in flat}
        params = {k: flat.pop(k) for k in list(flat) if k in self.init.params}
        parts = {"init": {"items": tuple(sorted((self.init.params | params).items()))}} if params else {}
        for k, v in flat.items():
            sec, field_ = _WHERE[k]
            parts.setdefault(sec, {})[field_.name] = v
        return dataclasses.replace(self, **top, **{s: dataclasses.replace(getattr(self, s), **kw)
                                                   for s, kw in parts.items()})


# ---------------------------------------------------------------------------------------
# the keys: section fields by flat name, and the initial conditions' own parameters
# ---------------------------------------------------------------------------------------
def _flat_name(field_: dataclasses.Field) -> str:
    return field_.metadata.get("flat") or field_.name


_WHERE = {f.name: (None, f) for f in dataclasses.fields(Scene) if "key" in f.metadata} | {
    _flat_name(f): (sec, f) for sec, cls in SECTIONS.items() for f in dataclasses.fields(cls) if "key" in f.metadata}
_PPC = dict(lo=0.0, hi=MAX_PPC)
INIT_KEYS = {  # the initial conditions' parameters (their defaults are in initial.py)
    "ppc": Key("real", "particles per cell (void: outside the void)", **_PPC),
    "ppc_outer": Key("real", "particles per cell outside the outer shape", **_PPC),
    "ppc_inner": Key("real", "particles per cell inside the inner shape", **_PPC),
    "void_lo": Key("real", "void: where the void starts along axis 0 (length units; may lie outside)"),
    "void_hi": Key("real", "void: where the void ends along axis 0 (length units, >= void_lo)"),
    "outer_r": Key("real", "radius of the outer shape (unit box)", lo=0.0),
    "inner_r": Key("real", "radius of the inner shape (unit box)", lo=0.0),
    "inner_x": Key("real", "spheres: offset of the inner sphere along x"),
    "inner_y": Key("real", "spheres: offset of the inner sphere along y"),
    "inner_z": Key("real", "spheres: offset of the inner sphere along z"),
}
INIT_AXES = {"ellipses": 2, "spheres": 3}  # initial conditions drawn for one dimension only
KEYS = {k: f.metadata["key"] for k, (_, f) in _WHERE.items()} | INIT_KEYS  # every key by flat name


def _default(name: str) -> Any:
    """A key's default as --help shows it (None: none, or it depends on the scene)."""
    if name in _WHERE:
        d = _WHERE[name][1].default
        return None if d is dataclasses.MISSING else d
    for f in initial.REGISTRY.values():
        p = inspect.signature(f).parameters.get(name)
        if p is not None:
            return p.default
    return None


def keys_help() -> str:
    """Every scene key, table by table: name, doc, what it takes, default (``--help`` and the README)."""
    tables: dict[str, list[str]] = {}
    for name, k in KEYS.items():
        sec = _WHERE[name][0] if name in _WHERE else "init"
        d = _default(name)
        shown = "" if d in (None, (), "") else f"; default {str(d).lower() if isinstance(d, bool) else d}"
        tables.setdefault(f"[{sec}]" if sec else "top level", []).append(
            f"  {name:<17} {k.doc} ({k.describe()}{shown})")
    return "\n".join(f"{t}\n" + "\n".join(lines) for t, lines in tables.items())


# ---------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------
def available_scenes() -> list[str]:
    return sorted(p.stem for p in SCENE_DIR.glob("*.toml"))


def _read_toml(name_or_path: str | Path) -> tuple[str, dict[str, Any]]:
    path = Path(name_or_path)
    if path.suffix != ".toml" or not path.exists():
        path = SCENE_DIR / f"{name_or_path}.toml"
    if not path.exists():
        raise ConfigError(
            f"unknown scene '{name_or_path}': give a .toml path or one of {', '.join(available_scenes())}"
        )
    try:
        raw = tomllib.loads(path.read_bytes().decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc}): fix the file") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not UTF-8 text: give a TOML scene file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path} is a directory: give a .toml scene file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror}): check the path and its permissions") from None
    return path.stem, raw


def _flatten(raw: dict[str, Any]) -> dict[str, Any]:
    """A scene file's tables as flat keys (``[method] name`` is ``method``, ``[init] name`` is ``init``);
    a key may also stand at the top level."""
    flat: dict[str, Any] = {}
    for table, value in raw.items():
        if table not in SECTIONS or not isinstance(value, dict):
            flat[table] = value
            continue
        for sub, v in value.items():
            name = table if sub == "name" and table in ("init", "method") else sub
            home = _WHERE[name][0] if name in _WHERE else ("init" if name in INIT_KEYS else table)
            if home != table:
                raise ConfigError(f"[{table}] {sub}: this key belongs "
                                  + (f"in [{home}]" if home else "at the top of the file, before any table"))
            flat[name] = v
    return flat


def load_scene(name_or_path: str | Path, **overrides: Any) -> Scene:
    """Read a scene by name (``scenes/NAME.toml``) or path, apply flat overrides, validate.

    Raises
    ------
    ConfigError
        With a one-line message naming the key and what to change.
    """
    name, raw = _read_toml(name_or_path)
    flat = _flatten(raw)
    flat.update(overrides)
    flat.setdefault("name", name)
    return make_scene(flat)


def make_scene(flat: dict[str, Any]) -> Scene:
    """Validate a flat dict of scene keys (section keys by flat name plus the initial condition's
    parameters) into a :class:`Scene`."""
    flat = {k: _plain(v) for k, v in flat.items()}
    init = _init_keys(flat)
    grid = _grid_keys(flat, init.name)
    kw: dict[str, dict[str, Any]] = {sec: {} for sec in (None, *SECTIONS) if sec not in ("grid", "init")}
    for name, (sec, field_) in _WHERE.items():
        k = field_.metadata["key"]
        if name in flat and k.kind != "special" and sec not in ("grid", "init"):
            kw[sec][field_.name] = k.check(name, flat[name])
    kw[None]["name"] = _file_name(kw[None].get("name", init.name))
    method = kw["method"].get("name", MethodKeys.name)
    if flat.get("compare") not in (None, "none"):
        if flat["compare"] not in METHODS:
            raise ConfigError(f"compare = {flat['compare']!r}: use one of {', '.join(METHODS)}, or none")
        if flat["compare"] != method:  # comparing with itself: nothing
            kw["method"]["compare"] = flat["compare"]
    kw["stats"].update(_stats_keys(flat, kw["time"].get("t_end", TimeKeys.t_end)))
    scene = Scene(grid=grid, init=init, **kw.pop(None), **{s: SECTIONS[s](**v) for s, v in kw.items() if s})
    _check_choices(scene)
    _check_sizes(scene)
    _check_time_step(scene)
    check_memory(scene)
    return scene


def _init_keys(flat: dict[str, Any]) -> InitKeys:
    """Take the initial condition and its parameters out of ``flat``; refuse keys nobody takes."""
    if "init" not in flat:
        raise ConfigError("the scene names no initial condition: add [init] name = ...")
    ic_name = flat.pop("init")
    if not isinstance(ic_name, str) or ic_name not in initial.REGISTRY:
        raise ConfigError(f"unknown initial condition {ic_name!r}: use one of {', '.join(initial.REGISTRY)}")
    ic_sig = inspect.signature(initial.REGISTRY[ic_name])
    ic_keys = [p for p in ic_sig.parameters if p != "x"]
    params = {k: flat.pop(k) for k in list(flat) if k in ic_keys}
    for k, p in ic_sig.parameters.items():
        if k != "x" and k not in params:
            if p.default is inspect.Parameter.empty:
                raise ConfigError(f"initial condition '{ic_name}' needs '{k}': set it in [init] or with --set {k}=...")
            params[k] = p.default
    for k, v in params.items():
        params[k] = INIT_KEYS.get(k, Key("real", "")).check(k, v)
    unknown = [k for k in flat if k not in _WHERE]
    if unknown:
        if unknown[0] in INIT_KEYS:
            raise ConfigError(f"'{unknown[0]}' is not a parameter of initial condition '{ic_name}': "
                              f"its parameters are {', '.join(ic_keys)}")
        valid = sorted(set(_WHERE) - {"name", "init"} | set(ic_keys))
        raise ConfigError(f"unknown key '{unknown[0]}': valid keys are {', '.join(valid)}")
    return InitKeys(ic_name, tuple(sorted(params.items())))


def _grid_keys(flat: dict[str, Any], ic_name: str) -> GridKeys:
    cells = _int_tuple("cells", flat.get("cells"))
    dim = len(cells)
    if not 1 <= dim <= 3:
        raise ConfigError(f"cells has {dim} entries: give 1, 2 or 3 cell counts")
    if min(cells) < 2:
        raise ConfigError(f"cells = {list(cells)}: every axis needs at least 2 cells")
    if INIT_AXES.get(ic_name, dim) != dim:
        raise ConfigError(f"cells = {list(cells)}: initial condition '{ic_name}' is {INIT_AXES[ic_name]}D, "
                          f"give {INIT_AXES[ic_name]} cell counts")
    lengths = flat.get("lengths", [1.0] * dim)
    lengths = tuple(_number("lengths", v) for v in (lengths if isinstance(lengths, list) else [lengths] * dim))
    if len(lengths) != dim:
        raise ConfigError(f"lengths has {len(lengths)} entries but cells has {dim}: give one length per axis")
    boundary = _per_side("boundary", flat.get("boundary", "periodic"), dim, str)
    for axis, (lo, hi) in enumerate(boundary):
        for kind in (lo, hi):
            if kind not in BOUNDARY_KINDS:
                raise ConfigError(f"boundary '{kind}' on axis {axis}: use one of {', '.join(BOUNDARY_KINDS)}")
        if (lo == "periodic") != (hi == "periodic"):
            raise ConfigError(f"axis {axis} is periodic on one side only: make both sides periodic or neither")
    reservoir = _per_side("reservoir_ppc", flat.get("reservoir_ppc", 0.0), dim, float)
    for r in (r for sides in reservoir for r in sides):
        Key("real", "", **_PPC).check("reservoir_ppc", r)
    return GridKeys(cells, lengths, boundary, reservoir)


def _stats_keys(flat: dict[str, Any], t_end: float) -> dict[str, Any]:
    """The special keys of ``[stats]``: output times (``t_end`` always one), ``t_equil``, histogram."""
    kw: dict[str, Any] = {}
    if flat.get("t_equil") is not None:
        kw["t_equil"] = _number("t_equil", flat["t_equil"], positive=False)
        if not 0 <= kw["t_equil"] < t_end:
            raise ConfigError(f"t_equil = {kw['t_equil']}: it must lie in [0, t_end = {t_end})")
    outs = flat.get("output_times", [t_end])
    outs = tuple(_number("output_times", t, positive=False) for t in (outs if isinstance(outs, list) else [outs]))
    if any(t < 0 for t in outs):
        raise ConfigError(f"output_times {list(outs)}: times must be >= 0")
    # times past t_end (say after --t-end shortened a run) are dropped; t_end itself is always written
    kw["output_times"] = tuple(sorted({t for t in outs if t < t_end} | {t_end}))
    if flat.get("histogram") is not None:
        h = _int_tuple("histogram", flat["histogram"], minimum=None)
        if len(h) != 2 or h[0] >= h[1]:
            raise ConfigError("histogram: give [lo, hi] in particles per cell with lo < hi")
        kw["histogram"] = h
    return kw


def _check_choices(scene: Scene) -> None:
    """Keys that are valid alone but not together."""
    m, h = scene.method, scene.hybrid
    if m.particle_init == "exact_uniform" and (scene.init.name != "uniform" or m.name != "particle"):
        raise ConfigError("particle_init = 'exact_uniform' needs init 'uniform' and method 'particle'")
    if h.max_box < 2 * h.min_box:
        raise ConfigError(f"max_box = {h.max_box} < 2 min_box = {2 * h.min_box}: "
                          "raise max_box so an oversized box can be halved")
    cells = scene.grid.cells
    if m.name == "hybrid" and 32 - math.ceil(math.log2(math.prod(n + 2 for n in cells))) < ID_BITS_MIN:
        raise ConfigError(f"cells = {list(cells)}: too many cells for the hybrid's 32-bit particle ids; "
                          f"use at most about {2 ** (32 - ID_BITS_MIN):.3g} cells")


def _plain(value: Any) -> Any:
    """Python callers' tuples as lists and NumPy scalars as Python numbers, as TOML gives them."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value.item() if isinstance(value, np.generic) else value


def _file_name(name: Any) -> str:
    """The scene name, which names the output files: a plain file name, so they stay inside --out."""
    if not isinstance(name, str) or not NAME_RE.fullmatch(name):
        raise ConfigError(f"name = {name!r}: give a plain file name of letters, digits, '.', '_' or '-' "
                          "(it names the output files inside --out)")
    return name


def _check_sizes(scene: Scene) -> None:
    """Sizes whose derived quantities would overflow, underflow or mean nothing."""
    cells = math.prod(scene.grid.cells)
    if scene.method.ensemble * cells > MAX_FIELD:
        raise ConfigError(f"ensemble x cells = {scene.method.ensemble * cells:,}: Taichi fields hold at most "
                          f"{MAX_FIELD:,} "
                          "entries; lower the ensemble or the cells (or split it: --executor dask)")
    vol = scene.grid.cell_volume
    if not (math.isfinite(vol) and vol > 0 and math.isfinite(1 / vol) and scene.dt > 0 and math.isfinite(scene.dt)
            and all(math.isfinite(h * h) and h * h > 0 for h in scene.grid.dx)):
        raise ConfigError(f"lengths = {list(scene.grid.lengths)}, C = {scene.time.C}: the cell size or time step "
                          "under- or "
                          "overflows double precision; give lengths and C nearer 1")
    steps = scene.time.t_end / scene.dt
    if steps < 0.5:
        raise ConfigError(f"t_end = {scene.time.t_end:g} is shorter than one time step dt = {scene.dt:.4g}: "
                          f"raise t_end (or C)")
    if steps > MAX_STEPS:
        raise ConfigError(f"t_end = {scene.time.t_end:g} is {steps:.3g} steps of dt = {scene.dt:.4g}: at most "
                          f"{MAX_STEPS:,} steps fit the random-number counter; lower t_end or raise C")
    if scene.stats.t_equil is not None and scene.n_steps - round(scene.stats.t_equil / scene.dt) < 1:
        raise ConfigError(f"t_equil = {scene.stats.t_equil:g} leaves no step to sample before t_end: lower t_equil")
    p = scene.init.params
    if scene.init.name == "void" and not p["void_lo"] <= p["void_hi"]:
        raise ConfigError(f"void_lo = {p['void_lo']}, void_hi = {p['void_hi']}: give void_lo <= void_hi")


def _check_time_step(scene: Scene) -> None:
    limit = scene.time.C / scene.stability_number
    if scene.stability_number >= 1 and not scene.time.allow_unstable and scene.method.name != "particle":
        raise ConfigError(
            f"C = {scene.time.C} is beyond the explicit stability limit C < {limit:.4g} of the FV scheme on this grid: "
            f"lower C (e.g. --set C={limit / 2:.4g}) or set allow_unstable=true for a stability experiment"
        )
    if scene.method.name == "hybrid" and scene.n_steps * scene.hybrid.particle_substeps >= HYBRID_STEP_LIMIT:
        raise ConfigError(
            f"t_end = {scene.time.t_end} is {scene.n_steps * scene.hybrid.particle_substeps:,} particle steps; "
            "the hybrid numbers "
            f"particle births in 27 bits: give fewer than {HYBRID_STEP_LIMIT:,} (shorter t_end, larger C or fewer "
            "particle_substeps)")
    if scene.method.name in ("particle", "hybrid") and scene.clamp_probability > CLAMP_WARN:
        warnings.warn(
            f"C = {scene.time.C}: a particle step is clamped to ±Δx with probability {scene.clamp_probability:.2g} "
            f"per axis and step (> {CLAMP_WARN:g}); lower C to make clamping rare",
            ClampWarning,
            stacklevel=3,
        )


# ---------------------------------------------------------------------------------------
# what a run needs: memory, steps, time
# ---------------------------------------------------------------------------------------
SPDE_RATE = {1: 1e8, 2: 2e7, 3: 2e7}  # cell-updates per second on 2 CPU cores, by dimension (RESULTS.md, rounded down)
PARTICLE_RATE = 3e7  # particle steps per second, likewise
HYBRID_PARTICLE_RATE = 1.5e7  # the hybrid's particle part (ghost fill, walk, cap, compaction) per particle-step
REGRID_RATE = 1e7  # grid cells per second a hybrid regrid or on-demand extension handles (host masks, lists)


def _particles(scene: Scene) -> float:
    """The particles per member the particle method must hold (an upper bound for huge grids)."""
    from .particles import ParticleSolver  # pure NumPy; imported here to keep config light

    m = math.prod(scene.grid.cells)
    if m <= 10**7:
        return ParticleSolver.capacity_for(Grid.from_scene(scene), scene.initial_ppc)
    most = math.ceil(_ppc_max(scene)) * m  # every cell at the largest density
    return capacity(most) if Grid.from_scene(scene).has_dirichlet else most


def _ppc_max(scene: Scene) -> float:
    """The largest initial or reservoir density, in particles per cell."""
    ppc = [v for k, v in scene.init.params.items() if k.startswith("ppc")]
    return max(ppc + [Grid.from_scene(scene).reservoir_ppc_max])


def memory_estimate(scene: Scene) -> dict[str, float]:
    """Bytes a run needs, by part: solver fields, particles, host copies, statistics, histogram.

    Rough (within a factor of about 2) but computed before anything is allocated; the hybrid's
    particle pool grows with its region and is counted for the threshold density everywhere.
    """
    cells = math.prod(scene.grid.cells)
    mc = scene.method.ensemble * cells  # member-cells
    real = 4 if scene.method.precision == "f32" else 8
    est = {"fields": 0.0, "particles": 0.0}
    for method in (scene.method.name, scene.method.compare):
        if method in ("fv", "gaussian", "hybrid"):
            est["fields"] += mc * (1 + scene.grid.dim) * real
        if method == "hybrid":
            est["fields"] += mc * 32  # region, ghost ring, cell lists, counts
            # two buffers of slots for every member at the threshold density everywhere
            per_member = capacity(min(scene.hybrid.threshold, _ppc_max(scene)) * cells)
            est["particles"] += 2 * scene.method.ensemble * per_member * (scene.grid.dim * real + 8)
        if method == "particle":
            est["fields"] += mc * 4
            # with reservoirs: ids (8 bytes) and two buffers plus a keep flag (the pool compacts)
            d = Grid.from_scene(scene).has_dirichlet
            per_slot = (1 + d) * (scene.grid.dim * real + 8 * d) + d
            est["particles"] += scene.method.ensemble * _particles(scene) * per_slot
    est["host copies"] = 3 * mc * 8  # density read back as float64, and its statistics update
    rows = 1 if scene.stats.t_equil is not None else len(scene.stats.output_times)
    est["statistics"] = (rows + 1) * cells * 12 * 8  # moments and accumulators per row
    if scene.stats.histogram:
        est["histogram"] = (rows + 1) * cells * (scene.stats.histogram[1] - scene.stats.histogram[0] + 1) * 8
    return est


def machine_memory() -> int:
    """Bytes of memory this process may use: physical memory, or a smaller cgroup limit."""
    have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit.isdigit():
            have = min(have, int(limit))
    except OSError:
        pass
    return have


def check_memory(scene: Scene) -> None:
    """Refuse, with one line, a scene that needs more memory than this machine has."""
    est = memory_estimate(scene)
    need, have = sum(est.values()), machine_memory()
    if need > have:
        part = max(est, key=est.get)
        hint = {"histogram": "narrow histogram", "particles": "lower ppc or the ensemble, or use fv or hybrid"}
        raise ConfigError(f"the run needs about {need / 2**30:.3g} GiB ({part} {est[part] / 2**30:.3g} GiB) but this "
                          f"machine has {have / 2**30:.3g} GiB: {hint.get(part, 'lower cells or the ensemble')}")


def work_estimate(scene: Scene) -> tuple[int, float]:
    """``(steps, seconds)``: the steps of the run and a rough wall time on 2 CPU cores.

    The hybrid adds its particles, counted as the cells tagged at the start holding ``threshold``
    each (half that in a fixed region, which fills from its start), and a regrid's pass over the
    grid every step when extensions are on (``regrid_floor > 0``), else every ``regrid_interval``
    steps. Measured against (benchmarks/RESULTS.md): sphere3d 7.0 min estimated, 6.6 min run;
    ellipse2d 49 s and 51–56 s; void1d with 20,000 members 32 s and 25 s (fv), 299 s and 211 s (hybrid).
    """
    cells = math.prod(scene.grid.cells)
    mc = scene.method.ensemble * cells
    per_step = 0.0
    for method in (scene.method.name, scene.method.compare):
        if method in ("fv", "gaussian", "hybrid"):
            per_step += mc / SPDE_RATE[scene.grid.dim]
        if method == "particle":
            per_step += scene.method.ensemble * _particles(scene) / PARTICLE_RATE
        if method == "hybrid":
            h = scene.hybrid
            tagged = int(np.count_nonzero(scene.initial_ppc < h.threshold)) if cells <= 10**7 else cells
            held = h.threshold if h.regrid_interval else h.threshold / 2  # particles per tagged cell
            per_step += scene.method.ensemble * tagged * held / HYBRID_PARTICLE_RATE
            if h.regrid_interval:
                per_step += mc / REGRID_RATE / (1 if h.regrid_floor > 0 else h.regrid_interval)
    return scene.n_steps, scene.n_steps * per_step


# ---------------------------------------------------------------------------------------
# run options that are not scene keys
# ---------------------------------------------------------------------------------------
def check_options(scene: Scene, *, out: str | Path | None = None, executor: str = "local",
                  workers: int | None = None, chunk: int | None = None, threads: int | None = None,
                  scheduler: str | None = None, checkpoint_every: int = 0, restart: str | Path | None = None,
                  movie: bool = False) -> None:
    """Check the options of a run (the command line's, or :func:`ti_dk.run`'s) before anything starts."""
    def whole(name: str, value: Any, lo: int, hi: int | None = None) -> None:
        if value is None:
            return
        Key("int", "", lo=lo, hi=hi).check(name, value)

    whole("--threads", threads, 1, 4096)
    whole("--checkpoint-every", checkpoint_every, 0, MAX_STEPS)
    whole("--workers", workers, 1, 4 * (os.cpu_count() or 1) if scheduler is None else 100_000)
    whole("--chunk", chunk, 1, MAX_MEMBERS)
    if executor == "dask":
        for flag, given in (("--checkpoint-every", checkpoint_every), ("--restart", restart), ("--movie", movie)):
            if given:
                raise ConfigError(f"{flag} is for the local executor: drop it or use --executor local "
                                  "(a stopped Dask run resumes from its finished chunks)")
    else:
        for flag, given in (("--workers", workers), ("--chunk", chunk), ("--scheduler", scheduler)):
            if given is not None:
                raise ConfigError(f"{flag} is for --executor dask: drop it or add --executor dask")
    if restart is not None and not Path(restart).is_file():
        raise ConfigError(f"--restart {restart}: no such checkpoint file")
    if out is not None:
        p = Path(out)
        parent = next((q for q in (p, *p.parents) if q.exists()), None)
        if parent is not None and not parent.is_dir():
            raise ConfigError(f"--out {out}: {parent} is a file: give a directory")
        if parent is not None and not os.access(parent, os.W_OK | os.X_OK):
            raise ConfigError(f"--out {out}: {parent} is not writable here; give a directory you can write")


# ---------------------------------------------------------------------------------------
# typed readers with one-line messages
# ---------------------------------------------------------------------------------------
def _number(key_: str, value: Any, positive: bool = True) -> float:
    return Key("real", "", lo=0.0 if positive else None, above=positive).check(key_, value)


def _int(key_: str, value: Any, minimum: int | None = 1) -> int:
    return Key("int", "", lo=minimum).check(key_, value)


def _int_tuple(key_: str, value: Any, minimum: int | None = 1) -> tuple[int, ...]:
    if value is None:
        raise ConfigError(f"the scene has no '{key_}': add it (e.g. [grid] cells = [100])")
    items = value if isinstance(value, list) else [value]
    return tuple(_int(key_, v, minimum) for v in items)


def _per_side(key_: str, value: Any, dim: int, kind: type) -> tuple[tuple[Any, Any], ...]:
    """Expand a scalar, a per-axis list, or a per-axis list of [lo, hi] pairs."""
    def one(v: Any) -> Any:
        if kind is float:
            return _number(key_, v, positive=False)
        if not isinstance(v, str):
            raise ConfigError(f"{key_} = {v!r}: give a name")
        return v

    if not isinstance(value, list):
        return tuple((one(value), one(value)) for _ in range(dim))
    if len(value) != dim:
        raise ConfigError(f"{key_} has {len(value)} entries but the grid has {dim} axes: give one per axis")
    out = []
    for v in value:
        if isinstance(v, list):
            if len(v) != 2:
                raise ConfigError(f"{key_}: give [lo, hi] for each axis")
            out.append((one(v[0]), one(v[1])))
        else:
            out.append((one(v), one(v)))
    return tuple(out)


def parse_value(text: str, key_: str | None = None) -> Any:
    """Parse a ``--set key=value`` value as TOML (numbers, lists, booleans), else a string; for a
    key that takes text or a choice, the text as given (``--set name=2024``)."""
    if key_ in KEYS and KEYS[key_].kind in ("text", "choice") and not text.startswith(('"', "'")):
        return text
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
