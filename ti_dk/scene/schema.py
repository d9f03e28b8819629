"""Every scene key declared once: frozen sections per table, and the :class:`Scene` that holds them.

A scene file groups its keys in tables (``[grid]``, ``[init]``, ``[time]``, ``[method]``,
``[hybrid]``, ``[stats]``, ``[output]``); the loaded :class:`Scene` holds one frozen section per
table (``scene.grid.cells``, ``scene.method.name``, ``scene.hybrid.threshold``). Every key name is
unique across tables, so every key can also be given flat: at the top of a file, or overridden by
its bare name (``load_scene("void1d", ppc=5, C=0.05)`` or ``--set ppc=5``). Densities in scene
files are in particles per cell; inside the solvers they are number densities (particles per unit
volume).

Every key is declared once, as a section field carrying a :class:`Key` (kind, limits or
choices, a one-line doc); validation (:func:`ti_dk.scene.load.make_scene`), ``--set`` parsing and
``--help`` (:func:`keys_help`) all read that declaration. The run options that are not scene keys
(``--out``, Dask sizes, checkpoints) are checked by :func:`ti_dk.control.options.check_options`,
and what a scene needs (memory, steps, time) by :func:`ti_dk.scene.estimates.memory_estimate` and
:func:`~ti_dk.scene.estimates.work_estimate`, all before Taichi starts.
"""
from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib.resources
import inspect
import math
import re
from dataclasses import dataclass
from typing import Any
from pathlib import Path

import numpy as np

from . import initial
from ..core.expr import Potential
from ..core.grid import Geometry
from ..core.errors import ConfigError
from ..hybrid.clustering import RegridParams
from ..pools import LAYOUTS as POOL_LAYOUTS


def scene_dir() -> Path:
    """Where the scene files are: the package data ``ti_dk.scenes`` through :mod:`importlib.resources`.

    An installed ti_dk (wheel or editable) has it: pyproject.toml installs the top-level
    ``scenes/`` folder as that package. A source checkout imported without installing does not;
    then its own ``scenes/`` folder, next to ``ti_dk/``.
    """
    try:
        # the package's own name: benchmarks/bench_ab.py imports copies of it under other names
        return Path(str(importlib.resources.files(__name__.split(".")[0] + ".scenes")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "scenes"


SCENE_DIR = scene_dir()
METHODS = ("fv", "gaussian", "particle", "hybrid")
SPDES = ("fv", "gaussian")  # the SPDE a hybrid run keeps on the whole grid
GHOST_PROFILES = ("mean", "linear", "uniform")  # how sampled particles lie in their cell (see HybridSolver)
REGIONS = ("tiles", "boxes")  # how the particle region covers the tagged cells (hybrid.tiles, hybrid.clustering)
REGION_SOURCES = ("mean", "member")  # whose density a scheduled regrid tags (hybrid.regridder.Regridder.regrid)
BOUNDARY_KINDS = ("periodic", "neumann", "dirichlet")
PRECISIONS = ("f32", "f64")
PARTICLE_INITS = ("per_cell", "exact_uniform", "exact")
CLAMP_WARN = 1e-3  # warn when a particle step is clamped with more than this probability
MAX_STEPS = 2**32 - 1  # the step is one 32-bit word of every random-number counter (rng.py)
MAX_MEMBERS = 2**32  # so is the member index
MAX_FIELD = 2**31 - 1  # Taichi indexes a field with 32-bit integers: members x cells must fit
MAX_PPC = 1e15  # particles per cell: beyond, counts are not exact in f64 and fourth moments overflow
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")  # a scene name is a plain file name
_RG = RegridParams()  # the clustering defaults, written once in clustering.py
SERIES_POINTS = 200  # a run's per-member series without observables: about this many records


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
            raise ConfigError(f"{name} = {_shown(value)}: give {'a whole number' if self.kind == 'int' else 'a number'}")
        if self.kind == "real":
            try:
                value = float(value)
            except OverflowError:  # a whole number beyond the largest float, 1.8e308
                raise ConfigError(f"{name} = {_shown(value)}: beyond double precision; give {self.describe()}") from None
        below = self.lo is not None and (value < self.lo or (self.above and value == self.lo))
        big = self.kind == "int" and self.hi is None and abs(value) > 2**63 - 1  # no key takes more than 64 bits
        if (self.kind == "real" and not math.isfinite(value)) or below or big or (self.hi is not None and value > self.hi):
            raise ConfigError(f"{name} = {_shown(value)}: give {self.describe()}" + " below 2^63" * big)
        return value


def did_you_mean(name: Any, names) -> str:
    """``"did you mean a or b? "``: the ``names`` nearest a misspelt ``name`` (``difflib``), or ``""``."""
    near = difflib.get_close_matches(str(name), list(names), n=3)
    return f"did you mean {' or '.join(near)}? " if near else ""


def _shown(value: Any) -> str:
    """A value as a message shows it: a whole number of many digits by its first ones and its size."""
    text = repr(value)
    return text if len(text) <= 24 else f"{text[:8]}… (a {len(text.lstrip('-'))}-digit number)"


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
    potential: Potential | None = key(  # parsed once, by load._grid_keys (None: none)
        "special", "external potential U in units of k_BT, drift -grad(U)/2 (default none)", None,
        form='a formula in x, y, z with + - * / ** sin cos tan exp log sqrt abs tanh atan step pi, '
             'e.g. "0.5*((x-0.5)/0.08)**2"')


@dataclass(frozen=True)
class InitKeys:
    """``[init]``: the initial condition (a function of :mod:`ti_dk.scene.initial`) and its own keys."""

    name: str = key("special", "the initial condition ([init] name = ...)", flat="init",
                    form="one of " + ", ".join(initial.REGISTRY))
    items: tuple[tuple[str, Any], ...] = ()  # its parameters (INIT_KEYS), sorted by name

    @property
    def params(self) -> dict[str, Any]:
        """The initial condition's own parameters by name."""
        return dict(self.items)


@dataclass(frozen=True)
class TimeKeys:
    """``[time]``: explicit steps ``Δt = C · min(Δx_a)²`` up to ``t_end``."""

    C: float = key("real", "time step dt = C min(dx)^2", 0.0625, lo=0.0, above=True)
    t_end: float = key("real", "end time", 0.01, lo=0.0, above=True)
    allow_unstable: bool = key("bool", "accept C beyond the explicit stability limit (experiments)", False)
    runaway: str = key("choice", "a run that blows up (NaN, a density or mass change beyond any particle count): stop, "
                       "or continue (said once and marked in the file; NaN still stops)", "stop",
                       choices=("stop", "continue"))


@dataclass(frozen=True)
class MethodKeys:
    """``[method]``: what advances the density, for how many members, from which seed."""

    name: str = key("choice", "what advances the density ([method] name = ...)", "fv", flat="method", choices=METHODS)
    ensemble: int = key("int", "independent members", 1, lo=1, hi=MAX_MEMBERS)
    seed: int = key("int", "random seed: the same seed gives the same bits on any thread count", 0,
                    lo=0, hi=2**64 - 1)
    precision: str = key("choice", "floating-point precision of the solvers", "f64", choices=PRECISIONS)
    particle_init: str = key("choice", "particle method: ppc per cell, exactly ppc x cells uniform particles, or "
                             "exactly sum(ppc) particles with cells drawn by ppc",
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
    regrid_interval: int = key("int", "steps between regrids (0: the region is fixed)", 10, lo=0, hi=MAX_STEPS)
    buffer: int = key("int", "grow tagged cells by this many cells (at most the most cells along an axis)", _RG.buffer,
                      lo=0)
    region: str = key("choice", "how tagged cells are covered: tiles (each tile holding a tag, flagged on the device) "
                      "or boxes (Berger-Rigoutsos, the paper's)", _RG.region, choices=REGIONS)
    tile: int = key("int", "tiles: side in cells (0: 1 in 1D; from q̄ 2 in 2D and 1 in 3D; 4 from each member in 2D and 3D), at most the grid's largest side",
                    _RG.tile, lo=0)
    release: float = key("real", "tiles: a covered tile leaves only when all its cells (with the buffer) hold at "
                         "least this times threshold (hysteresis)", _RG.release, lo=1.0)
    region_from: str = key("choice", "whose density a scheduled regrid tags: the deterministic mean q-bar, one "
                           "region for every member (mean: exact while the region moves) or each member's own "
                           "(member: biased while it moves)", _RG.region_from, choices=REGION_SOURCES)
    grid_efficiency: float = key("real", "boxes: smallest tagged fraction of a box", _RG.efficiency,
                                 lo=0.0, hi=1.0, above=True)
    min_box: int = key("int", "boxes: smallest box side in cells (at most the most cells along an axis)", _RG.min_box,
                       lo=1)
    max_box: int = key("int", "boxes: largest box side in cells", _RG.max_box, lo=1, hi=MAX_FIELD)
    regrid_floor: float = key("real", "positivity guard: a member's uncovered cell below this times threshold is "
                              "covered before the next step (region_from mean: that cell and its buffer; member: "
                              "all its cells below threshold); 0: off (it follows each member's own density)",
                              _RG.regrid_floor, lo=0.0, hi=1.0)
    pool_layout: str = key("choice", "particle storage: flat (slots per member) or pointer (blocks of cells, "
                           "only where the region is)", "flat", choices=POOL_LAYOUTS)

    @property
    def regrid(self) -> RegridParams:
        """The region's settings as the hybrid reads them (``grid_efficiency`` as ``efficiency``)."""
        return RegridParams(threshold=self.threshold, buffer=self.buffer, efficiency=self.grid_efficiency,
                            min_box=self.min_box, max_box=self.max_box, regrid_floor=self.regrid_floor,
                            region_from=self.region_from,
                            region=self.region, tile=self.tile, release=self.release)


@dataclass(frozen=True)
class StatsKeys:
    """``[stats]``: when the ensemble's statistics are taken (rows at ``output_times``, or one
    pooled row for a stationary run, ``t_equil`` set)."""

    output_times: tuple[float, ...] = key("special", "times of the statistics rows and frames (t_end is always one)",
                                          (), form="a list of numbers in [0, t_end]")
    t_equil: float | None = key("special", "stationary runs: pool samples after this time (default: not stationary)",
                                None, form="a number in [0, t_end)")
    sample_every: int = key("int", "stationary runs: pool every k-th step; observables: record every k-th step", 1,
                            lo=1, hi=MAX_STEPS)
    histogram: tuple[int, int] | None = key("special", "per-cell histogram of particles per cell, one-particle bins",
                                            None, form="[lo, hi], whole numbers with lo < hi")
    structure_factor: bool = key("bool", "static structure factor S(k) of the count fluctuations per row "
                                 "(/stats/structure_factor, a PNG beside the frames)", False)
    observables: tuple[tuple[str, str], ...] = key(
        "special", "named regions whose particle count per member is recorded every sample_every steps "
        "(/observables/<name>; a cell counts when its centre is inside)", (),
        form='a table [observables] of name = "condition in x, y, z", e.g. left = "x < 0.5"')


@dataclass(frozen=True)
class OutputKeys:
    """``[output]``: what the run draws beyond its statistics."""

    movie_frames: int = key("int", "--movie: frames evenly spaced in time", 48, lo=1, hi=10_000)
    color_max: float = key("real", "2D/3D frames: top of the colour range in particles per cell (0: the largest "
                           "initial or reservoir density + 3 Poisson sd)", 0.0, lo=0.0, hi=MAX_PPC)
    color_scale: str = key("choice", "2D/3D frames: colour scale of the density (log: from 0.1 particles per cell "
                           "up, for a few particles beside many)", "linear", choices=("linear", "log"))
    length_si: float = key("real", "openPMD snapshots: the length unit L in metres (0: lengths and densities stay "
                           "pure numbers in units of L)", 0.0, lo=0.0, hi=1e30)
    diffusion_si: float = key("real", "openPMD snapshots, with length_si: D in m^2/s, so that times are in seconds "
                              "(the time unit is L^2/(2D); 0: times stay in it)", 0.0, lo=0.0, hi=1e30)

    def __post_init__(self):
        if self.diffusion_si and not self.length_si:
            raise ConfigError(f"diffusion_si = {self.diffusion_si:g} without length_si: the time unit L^2/(2D) needs "
                              "both; give length_si (L in metres) too, or neither")


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
        """The time step, C · min(Δx)²."""
        return self.time.C * min(self.grid.dx) ** 2

    @property
    def n_steps(self) -> int:
        """Steps to ``t_end`` (at least one)."""
        return max(1, round(self.time.t_end / self.dt))

    @property
    def output_steps(self) -> tuple[int, ...]:
        """The steps of the statistics rows: those nearest ``output_times``; stationary, the last."""
        if self.stats.t_equil is not None:
            return (self.n_steps,)
        return tuple(sorted({min(self.n_steps, round(t / self.dt)) for t in self.stats.output_times}))

    @property
    def observe_every(self) -> int:
        """Steps between a run's per-member records (``/series``, ``/observables``; step 0 and the
        last are recorded too): ``sample_every`` with observables, else about :data:`SERIES_POINTS` in all."""
        return self.stats.sample_every if self.stats.observables else max(1, self.n_steps // SERIES_POINTS)

    @property
    def clamp_probability(self) -> float:
        """Probability that one particle step (Δt / particle_substeps in the hybrid) along the finest axis
        exceeds Δx (and is clamped)."""
        substeps = self.hybrid.particle_substeps if self.method.name == "hybrid" else 1
        return math.erfc(min(self.grid.dx) / math.sqrt(2 * self.dt / substeps))

    @property
    def potential(self) -> Potential | None:
        """The external potential U (None without one): ``grid.potential``, parsed when the scene was made."""
        return self.grid.potential

    @functools.cached_property
    def initial_ppc(self) -> np.ndarray:
        """The initial condition (cell centres, or cell averages where it says so), in particles per
        cell: made at its first read, then kept (read-only; a new scene, as :func:`ti_dk.run` makes,
        reads a density file again)."""
        ppc = initial.density_ppc(self.init.name, self.init.params, self.grid.cells, self.grid.lengths,
                                  self.potential)
        ppc.setflags(write=False)
        return ppc

    def to_dict(self) -> dict[str, Any]:
        """The scene as nested tables, as a scene file writes it (the potential by its ``source``: a
        formula, or a callable's name)."""
        d = dataclasses.asdict(self)
        d["init"] = {"name": self.init.name, **self.init.params}
        d["grid"]["potential"] = self.potential.source if self.potential else ""
        return d

    def flat(self) -> dict[str, Any]:
        """Every key by its flat name (the form ``--set`` and :func:`load_scene` overrides take)."""
        out = {"name": self.name, "description": self.description, **self.init.params}
        for sec, field_ in WHERE.values():
            if sec is not None:
                out[_flat_name(field_)] = getattr(getattr(self, sec), field_.name)
        out["potential"] = self.potential or ""  # the parsed one, taken as it is (none: the key's empty text)
        return out

    def replace(self, **changes: Any) -> "Scene":
        """This scene with some keys changed by flat name, the initial condition's own parameters
        included, validated by the code that validates :func:`~ti_dk.scene.load.load_scene`
        (``load.make_scene``; another ``init`` drops this one's parameters, another ``t_end`` its
        place among the output times)."""
        flat = self.flat()
        if changes.get("init", self.init.name) != self.init.name:
            flat = {k: v for k, v in flat.items() if k not in self.init.params}
        if "t_end" in changes and "output_times" not in changes:
            flat["output_times"] = [t for t in self.stats.output_times if t != self.time.t_end]
        return MAKE_SCENE[0](flat | changes)


MAKE_SCENE: list = []  # load.make_scene, which load.py puts here (it imports this module, so not the reverse)


# ---------------------------------------------------------------------------------------
# the keys: section fields by flat name, and the initial conditions' own parameters
# ---------------------------------------------------------------------------------------
def _flat_name(field_: dataclasses.Field) -> str:
    return field_.metadata.get("flat") or field_.name


WHERE = {f.name: (None, f) for f in dataclasses.fields(Scene) if "key" in f.metadata} | {
    _flat_name(f): (sec, f) for sec, cls in SECTIONS.items() for f in dataclasses.fields(cls) if "key" in f.metadata}
PPC_LIMITS = dict(lo=0.0, hi=MAX_PPC)
SHAPE_LIMITS = dict(lo=0.0, hi=1e6)  # a shape in the unit box: far beyond it, its square would overflow
INIT_KEYS = {  # the initial conditions' parameters (their defaults are in initial.py)
    "ppc": Key("real", "particles per cell (void: outside the void)", **PPC_LIMITS),
    "ppc_outer": Key("real", "particles per cell outside the outer shape", **PPC_LIMITS),
    "ppc_inner": Key("real", "particles per cell inside the inner shape", **PPC_LIMITS),
    "void_lo": Key("real", "void: where the void starts along axis 0 (length units; may lie outside)"),
    "void_hi": Key("real", "void: where the void ends along axis 0 (length units, >= void_lo)"),
    "outer_r": Key("real", "radius of the outer shape (unit box)", **SHAPE_LIMITS),
    "inner_r": Key("real", "radius of the inner shape (unit box)", **SHAPE_LIMITS),
    "inner_x": Key("real", "spheres: offset of the inner sphere along x", lo=-SHAPE_LIMITS["hi"], hi=SHAPE_LIMITS["hi"]),
    "inner_y": Key("real", "spheres: offset of the inner sphere along y", lo=-SHAPE_LIMITS["hi"], hi=SHAPE_LIMITS["hi"]),
    "inner_z": Key("real", "spheres: offset of the inner sphere along z", lo=-SHAPE_LIMITS["hi"], hi=SHAPE_LIMITS["hi"]),
    "density": Key("text", "expression: particles per cell as a formula in x, y, z (like potential)"),
    "density_file": Key("text", "array: particles per cell from a .npy file or file.h5:/dataset, shaped like cells"),
}
INIT_AXES = {"ellipses": 2, "spheres": 3}  # initial conditions drawn for one dimension only
KEYS = {k: f.metadata["key"] for k, (_, f) in WHERE.items()} | INIT_KEYS  # every key by flat name


def _default(name: str) -> Any:
    """A key's default as --help shows it (None: none, or it depends on the scene)."""
    if name in WHERE:
        d = WHERE[name][1].default
        return None if d is dataclasses.MISSING else d
    for f in initial.REGISTRY.values():
        p = inspect.signature(f).parameters.get(name)
        if p is not None:
            return p.default
    return None


def keys_help() -> str:
    """Every scene key, table by table: name, doc, what it takes, default (``--help`` and docs/scenes.md)."""
    tables: dict[str, list[str]] = {}
    for name, k in KEYS.items():
        sec = WHERE[name][0] if name in WHERE else "init"
        d = _default(name)
        shown = "" if d in (None, (), "") else f"; default {str(d).lower() if isinstance(d, bool) else d}"
        tables.setdefault(f"[{sec}]" if sec else "top level", []).append(
            f"  {name:<17} {k.doc} ({k.describe()}{shown})")
    return "\n".join(f"{t}\n" + "\n".join(lines) for t, lines in tables.items())


