"""Scene parameters: frozen dataclasses, TOML loading, and the one place input is validated.

A scene file groups its keys in optional tables (``[grid]``, ``[init]``, ``[stats]``) for the
reader; the loaded :class:`Scene` is flat, so every key can be overridden by its bare name
(``load_scene("void1d", ppc=5, C=0.05)`` or ``--set ppc=5``). Densities in scene files are in
particles per cell; inside the solvers they are number densities (particles per unit volume).
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

import numpy as np

from . import initial
from .grid import Grid
from .regrid import RegridParams

SCENE_DIR = Path(__file__).resolve().parent.parent / "scenes"
METHODS = ("fv", "gaussian", "particle", "hybrid")
SPDES = ("fv", "gaussian")  # the SPDE a hybrid run keeps on the whole grid
GHOST_PROFILES = ("mean", "linear", "uniform")  # how sampled particles lie in their cell (see HybridSolver)
BOUNDARY_KINDS = ("periodic", "neumann", "dirichlet")
PRECISIONS = ("f32", "f64")
PARTICLE_INITS = ("per_cell", "exact_uniform")
ID_BITS_MIN = 8  # hybrid particle ids: birth cell in the high bits, at least this many for the index in the cell
HYBRID_STEP_LIMIT = 1 << 27  # hybrid: particle steps a run may take (birth steps live in 27 bits)
CLAMP_WARN = 1e-3  # warn when a particle step is clamped with more than this probability


class ConfigError(ValueError):
    """Bad scene input; the message says what to change."""


class ClampWarning(UserWarning):
    """The time step makes clamped particle steps (|step| > Δx) more likely than 1e-3."""


@dataclass(frozen=True)
class Scene:
    """A validated, immutable description of one run.

    Time step: ``dt = C · min(Δx_a)²``. Output rows are taken at the steps nearest to
    ``output_times``; with ``t_equil`` set, the run is treated as stationary and every
    ``sample_every``-th step after ``t_equil`` is pooled into one statistics row at ``t_end``.
    """

    name: str
    cells: tuple[int, ...]
    lengths: tuple[float, ...]
    boundary: tuple[tuple[str, str], ...]
    reservoir_ppc: tuple[tuple[float, float], ...]
    init: str
    init_params: tuple[tuple[str, Any], ...]
    method: str = "fv"
    C: float = 0.0625
    t_end: float = 0.01
    output_times: tuple[float, ...] = ()
    ensemble: int = 1
    seed: int = 0
    precision: str = "f64"
    threshold: float = 5.0
    t_equil: float | None = None
    sample_every: int = 1
    histogram: tuple[int, int] | None = None
    particle_init: str = "per_cell"
    spde: str = "fv"
    ghost_profile: str = "mean"
    particle_substeps: int = 1  # hybrid: particle steps of Δt/k per SPDE step (paper end of §3.1)
    compare: str | None = None  # a second method run on the same initial condition, drawn beside
    movie_frames: int = 48  # frames evenly spaced in time when a movie is asked for
    regrid_interval: int = 10
    buffer: int = 1
    grid_efficiency: float = 0.7
    min_box: int = 2
    max_box: int = 32
    allow_unstable: bool = False
    description: str = ""

    # -- derived geometry and time stepping ---------------------------------------------
    @property
    def grid(self) -> Grid:
        return Grid.from_scene(self)

    @property
    def dim(self) -> int:
        return self.grid.dim

    @property
    def dx(self) -> tuple[float, ...]:
        return self.grid.dx

    @property
    def cell_volume(self) -> float:
        return self.grid.cell_volume

    @property
    def dt(self) -> float:
        return self.C * min(self.dx) ** 2

    @property
    def n_steps(self) -> int:
        return max(1, round(self.t_end / self.dt))

    @property
    def output_steps(self) -> tuple[int, ...]:
        if self.t_equil is not None:
            return (self.n_steps,)
        return tuple(sorted({min(self.n_steps, round(t / self.dt)) for t in self.output_times}))

    @property
    def stability_number(self) -> float:
        """``Σ_a Δt/Δx_a²``: the explicit FV scheme is stable for values below 1."""
        return sum(self.dt / h**2 for h in self.dx)

    @property
    def clamp_probability(self) -> float:
        """Probability that one particle step (Δt / particle_substeps in the hybrid) along the finest axis
        exceeds Δx (and is clamped)."""
        substeps = self.particle_substeps if self.method == "hybrid" else 1
        return math.erfc(min(self.dx) / math.sqrt(2 * self.dt / substeps))

    @property
    def regrid(self) -> RegridParams:
        return RegridParams(threshold=self.threshold, buffer=self.buffer, efficiency=self.grid_efficiency,
                            min_box=self.min_box, max_box=self.max_box)

    @property
    def initial_ppc(self) -> np.ndarray:
        """The initial condition on the cell centres, in particles per cell."""
        return initial.density_ppc(self.init, self.params, self.cells, self.lengths)

    @property
    def params(self) -> dict[str, Any]:
        return dict(self.init_params)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["init_params"] = dict(self.init_params)
        return d


# ---------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------
_FIELDS = {f.name: f for f in dataclasses.fields(Scene)}
_SECTIONS = ("grid", "init", "stats")


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
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return path.stem, raw


def _flatten(raw: dict[str, Any]) -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in raw.items():
        if key in _SECTIONS and isinstance(value, dict):
            for sub, v in value.items():
                flat["init" if (key, sub) == ("init", "name") else sub] = v
        else:
            flat[key] = value
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
    """Validate a flat dict of scene keys (scene fields plus the initial condition's parameters)."""
    flat = dict(flat)
    if "init" not in flat:
        raise ConfigError("the scene names no initial condition: add [init] name = ...")
    ic_name = flat.pop("init")
    if ic_name not in initial.REGISTRY:
        raise ConfigError(f"unknown initial condition '{ic_name}': use one of {', '.join(initial.REGISTRY)}")
    ic_sig = inspect.signature(initial.REGISTRY[ic_name])
    ic_keys = [p for p in ic_sig.parameters if p != "x"]
    params = {k: flat.pop(k) for k in list(flat) if k in ic_keys}
    for k, p in ic_sig.parameters.items():
        if k != "x" and k not in params:
            if p.default is inspect.Parameter.empty:
                raise ConfigError(f"initial condition '{ic_name}' needs '{k}': set it in [init] or with --set {k}=...")
            params[k] = p.default
    for k, v in params.items():
        params[k] = _number(k, v, positive=False)
    unknown = [k for k in flat if k not in _FIELDS]
    if unknown:
        valid = sorted(set(_FIELDS) - {"init_params", "name"} | set(ic_keys))
        raise ConfigError(f"unknown key '{unknown[0]}': valid keys are {', '.join(valid)}")

    cells = _int_tuple("cells", flat.get("cells"))
    dim = len(cells)
    if not 1 <= dim <= 3:
        raise ConfigError(f"cells has {dim} entries: give 1, 2 or 3 cell counts")
    if min(cells) < 2:
        raise ConfigError(f"cells = {list(cells)}: every axis needs at least 2 cells")
    lengths = flat.get("lengths", [1.0] * dim)
    lengths = tuple(_number("lengths", v) for v in (lengths if isinstance(lengths, list) else [lengths]))
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
        if r < 0:
            raise ConfigError(f"reservoir_ppc = {r}: give a density >= 0 particles per cell")

    kw: dict[str, Any] = dict(
        name=str(flat.get("name", ic_name)),
        cells=cells,
        lengths=lengths,
        boundary=boundary,
        reservoir_ppc=reservoir,
        init=ic_name,
        init_params=tuple(sorted(params.items())),
        description=str(flat.get("description", "")),
    )
    for key in ("method", "precision", "particle_init", "spde", "ghost_profile"):
        if key in flat:
            kw[key] = flat[key]
    choices = {"method": METHODS, "precision": PRECISIONS, "particle_init": PARTICLE_INITS, "spde": SPDES,
               "ghost_profile": GHOST_PROFILES}
    for key, allowed in choices.items():
        value = kw.get(key, _FIELDS[key].default)
        if value not in allowed:
            raise ConfigError(f"{key} = {value!r}: use one of {', '.join(allowed)}")
    for key in ("C", "t_end", "threshold"):
        if key in flat:
            kw[key] = _number(key, flat[key])
    if flat.get("compare") not in (None, "none"):
        if flat["compare"] not in METHODS:
            raise ConfigError(f"compare = {flat['compare']!r}: use one of {', '.join(METHODS)}, or none")
        if flat["compare"] != kw.get("method", _FIELDS["method"].default):  # comparing with itself: nothing
            kw["compare"] = flat["compare"]
    for key in ("ensemble", "sample_every", "min_box", "max_box", "movie_frames", "particle_substeps"):
        if key in flat:
            kw[key] = _int(key, flat[key], minimum=1)
    for key in ("regrid_interval", "buffer"):
        if key in flat:
            kw[key] = _int(key, flat[key], minimum=0)
    if "grid_efficiency" in flat:
        kw["grid_efficiency"] = _number("grid_efficiency", flat["grid_efficiency"])
        if kw["grid_efficiency"] > 1:
            raise ConfigError(f"grid_efficiency = {kw['grid_efficiency']}: give a fraction in (0, 1]")
    if "seed" in flat:
        kw["seed"] = _int("seed", flat["seed"], minimum=0)
        if kw["seed"] >= 2**64:
            raise ConfigError("seed must be below 2**64")
    if "allow_unstable" in flat:
        if not isinstance(flat["allow_unstable"], bool):
            raise ConfigError("allow_unstable must be true or false")
        kw["allow_unstable"] = flat["allow_unstable"]
    t_end = kw.get("t_end", _FIELDS["t_end"].default)
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
    scene = Scene(**kw)
    if scene.particle_init == "exact_uniform" and (scene.init != "uniform" or scene.method != "particle"):
        raise ConfigError("particle_init = 'exact_uniform' needs init 'uniform' and method 'particle'")
    if scene.max_box < 2 * scene.min_box:
        raise ConfigError(f"max_box = {scene.max_box} < 2 min_box = {2 * scene.min_box}: "
                          "raise max_box so an oversized box can be halved")
    if scene.method == "hybrid" and 32 - math.ceil(math.log2(math.prod(n + 2 for n in cells))) < ID_BITS_MIN:
        raise ConfigError(f"cells = {list(cells)}: too many cells for the hybrid's 32-bit particle ids; "
                          f"use at most about {2 ** (32 - ID_BITS_MIN):.3g} cells")
    _check_time_step(scene)
    return scene


def _check_time_step(scene: Scene) -> None:
    limit = scene.C / scene.stability_number
    if scene.stability_number >= 1 and not scene.allow_unstable and scene.method != "particle":
        raise ConfigError(
            f"C = {scene.C} is beyond the explicit stability limit C < {limit:.4g} of the FV scheme on this grid: "
            f"lower C (e.g. --set C={limit / 2:.4g}) or set allow_unstable=true for a stability experiment"
        )
    if scene.method == "hybrid" and scene.n_steps * scene.particle_substeps >= HYBRID_STEP_LIMIT:
        raise ConfigError(
            f"t_end = {scene.t_end} is {scene.n_steps * scene.particle_substeps:,} particle steps; the hybrid numbers "
            f"particle births in 27 bits: give fewer than {HYBRID_STEP_LIMIT:,} (shorter t_end, larger C or fewer "
            "particle_substeps)")
    if scene.method in ("particle", "hybrid") and scene.clamp_probability > CLAMP_WARN:
        warnings.warn(
            f"C = {scene.C}: a particle step is clamped to ±Δx with probability {scene.clamp_probability:.2g} "
            f"per axis and step (> {CLAMP_WARN:g}); lower C to make clamping rare",
            ClampWarning,
            stacklevel=3,
        )


# ---------------------------------------------------------------------------------------
# typed readers with one-line messages
# ---------------------------------------------------------------------------------------
def _number(key: str, value: Any, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{key} = {value!r}: give a number")
    value = float(value)
    if not math.isfinite(value) or (positive and value <= 0):
        raise ConfigError(f"{key} = {value}: give a finite number{' > 0' if positive else ''}")
    return value


def _int(key: str, value: Any, minimum: int | None = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{key} = {value!r}: give a whole number")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{key} = {value}: give a whole number >= {minimum}")
    return value


def _int_tuple(key: str, value: Any, minimum: int | None = 1) -> tuple[int, ...]:
    if value is None:
        raise ConfigError(f"the scene has no '{key}': add it (e.g. [grid] cells = [100])")
    items = value if isinstance(value, list) else [value]
    return tuple(_int(key, v, minimum) for v in items)


def _per_side(key: str, value: Any, dim: int, kind: type) -> tuple[tuple[Any, Any], ...]:
    """Expand a scalar, a per-axis list, or a per-axis list of [lo, hi] pairs."""
    def one(v: Any) -> Any:
        if kind is float:
            return _number(key, v, positive=False)
        if not isinstance(v, str):
            raise ConfigError(f"{key} = {v!r}: give a name")
        return v

    if not isinstance(value, list):
        return tuple((one(value), one(value)) for _ in range(dim))
    if len(value) != dim:
        raise ConfigError(f"{key} has {len(value)} entries but the grid has {dim} axes: give one per axis")
    out = []
    for v in value:
        if isinstance(v, list):
            if len(v) != 2:
                raise ConfigError(f"{key}: give [lo, hi] for each axis")
            out.append((one(v[0]), one(v[1])))
        else:
            out.append((one(v), one(v)))
    return tuple(out)


def parse_value(text: str) -> Any:
    """Parse a ``--set key=value`` value as TOML (numbers, lists, booleans), else a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
