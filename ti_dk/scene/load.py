"""Loading a scene (TOML file or name, flat overrides) and the one place every value is validated:
kinds and limits from the schema, then what only the whole scene can say (sizes, the time step,
choices that fit together); the run options are checked in :mod:`ti_dk.control.options`."""
from __future__ import annotations

import inspect
import math
import os
import sys
import warnings
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

import numpy as np

from . import initial, observables
from ..core.expr import ExprError, Potential, quoted
from ..hybrid.ghosts import ID_BITS_MIN
from .checks import (COMPUTED, InputWarning, check_hybrid_sizes, check_initial, check_potential, check_time_step,
                     check_unused)
from .estimates import check_memory
from .schema import (BOUNDARY_KINDS, INIT_AXES, INIT_KEYS, KEYS, MAX_FIELD,
                     MAKE_SCENE, MAX_STEPS, METHODS, NAME_RE, PPC_LIMITS, SCENE_DIR, SECTIONS, WHERE,
                     ConfigError, GridKeys, InitKeys, Key, MethodKeys, Scene, TimeKeys, did_you_mean)

# ---------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------
def available_scenes() -> list[str]:
    """The names of the shipped scenes, which :func:`load_scene` takes as they are."""
    return sorted(p.stem for p in SCENE_DIR.glob("*.toml"))


def _read_toml(name_or_path: str | Path) -> tuple[str, dict[str, Any]]:
    path = Path(name_or_path)
    if path.suffix != ".toml" or not _exists(path):
        path = SCENE_DIR / f"{name_or_path}.toml"
    if not _exists(path):
        raise ConfigError(
            f"unknown scene '{name_or_path}': give a .toml path or one of {', '.join(available_scenes())}"
        )
    try:
        with initial.open_regular(path) as f:
            raw = tomllib.loads(f.read().decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc}): fix the file") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not UTF-8 text: give a TOML scene file") from None
    except (ValueError, RecursionError) as exc:  # a number of thousands of digits, lists thousands deep
        raise ConfigError(f"{path}: a value is out of reach ({_beyond(exc)}): fix the file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path} is a directory: give a .toml scene file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror}): check the path and its permissions") from None
    return path.stem, raw


def _exists(path: Path) -> bool:
    """Whether ``path`` exists; False for a name the file system cannot even look up (too long)."""
    try:
        return path.exists()
    except OSError:
        return False


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
            home = WHERE[name][0] if name in WHERE else ("init" if name in INIT_KEYS else table)
            if home != table:
                raise ConfigError(f"[{table}] {sub}: this key belongs "
                                  + (f"in [{home}]" if home else "at the top of the file, before any table"))
            if name in flat:  # also at the top of the file: one would silently win
                raise ConfigError(f"{name} is given twice, at the top of the file and in [{table}]: give it once")
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
    if overrides.get("init", flat.get("init")) != flat.get("init"):  # another initial condition: not the file's parameters
        flat = {k: v for k, v in flat.items() if k not in INIT_KEYS}
    flat.update(overrides)
    flat.setdefault("name", name)
    return make_scene(flat)


def make_scene(flat: dict[str, Any], initial_density: bool = True) -> Scene:
    """Validate a flat dict of scene keys (section keys by flat name plus the initial condition's
    parameters) into a :class:`Scene`; ``initial_density=False`` leaves the initial density to the
    caller (:func:`ti_dk.run` checks the one it runs from, by :func:`.checks.check_initial`)."""
    flat = {k: _plain(k, v) for k, v in flat.items()}
    init = _init_keys(flat)
    grid = _grid_keys(flat, init.name)
    kw: dict[str, dict[str, Any]] = {sec: {} for sec in (None, *SECTIONS) if sec not in ("grid", "init")}
    for name, (sec, field_) in WHERE.items():
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
    kw["stats"].update(observables.keys(flat.get("observables"), grid))  # [observables]: regions of this grid
    scene = Scene(grid=grid, init=init, **kw.pop(None), **{s: SECTIONS[s](**v) for s, v in kw.items() if s})
    try:
        _check_choices(scene)
        _check_sizes(scene)
        check_hybrid_sizes(scene)
        check_potential(scene)
        check_unused(scene)
        check_time_step(scene)
        check_memory(scene)
        if initial_density and scene.init.name in COMPUTED:
            check_initial(scene)
    except OverflowError:  # a length or time step near the float limits, squared
        raise ConfigError(f"lengths = {list(grid.lengths)}, C = {scene.time.C}: the cell size or time step under- or "
                          "overflows double precision; give lengths and C nearer 1") from None
    return scene


MAKE_SCENE.append(make_scene)  # Scene.replace validates by it


def scene_of(scene: Any) -> Scene:
    """What :func:`ti_dk.run` runs: a :class:`Scene` validated again as :func:`make_scene` validates
    (one made by hand or by ``dataclasses.replace`` too; its warnings were said when it was made),
    or a scene name or ``.toml`` path, loaded. The initial density is left to the run, which
    checks the one it runs from. Anything else: ``TypeError``."""
    if isinstance(scene, (str, os.PathLike)):
        return load_scene(scene)
    if not isinstance(scene, Scene):
        raise TypeError(f"run takes a Scene (from ti_dk.load_scene) or a scene name or .toml path, "
                        f"not {type(scene).__name__}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return make_scene(scene.flat(), initial_density=False)


def _init_keys(flat: dict[str, Any]) -> InitKeys:
    """Take the initial condition and its parameters out of ``flat``; refuse keys nobody takes."""
    if "init" not in flat:
        raise ConfigError("the scene names no initial condition: add [init] name = ...")
    ic_name = flat.pop("init")
    if not isinstance(ic_name, str) or ic_name not in initial.REGISTRY:
        raise ConfigError(f"unknown initial condition {ic_name!r}: use one of {', '.join(initial.REGISTRY)}")
    ic_sig = inspect.signature(initial.REGISTRY[ic_name])
    ic_keys = [p for p in ic_sig.parameters if p not in initial.CONTEXT]
    params = {k: flat.pop(k) for k in list(flat) if k in ic_keys}
    for k, p in ic_sig.parameters.items():
        if k not in initial.CONTEXT and k not in params:
            if p.default is inspect.Parameter.empty:
                raise ConfigError(f"initial condition '{ic_name}' needs '{k}': set it in [init] or with --set {k}=...")
            params[k] = p.default
    for k, v in params.items():
        params[k] = INIT_KEYS.get(k, Key("real", "")).check(k, v)
    unknown = [k for k in flat if k not in WHERE]
    if unknown:
        if unknown[0] in INIT_KEYS:
            raise ConfigError(f"'{unknown[0]}' is not a parameter of initial condition '{ic_name}': "
                              f"its parameters are {', '.join(ic_keys)}")
        valid = sorted(set(WHERE) - {"name", "init"} | set(ic_keys))
        raise ConfigError(f"unknown key '{unknown[0]}': {did_you_mean(unknown[0], valid)}valid keys are {', '.join(valid)}")
    return InitKeys(ic_name, tuple(sorted(params.items())))


def _grid_keys(flat: dict[str, Any], ic_name: str) -> GridKeys:
    cells = _int_tuple("cells", flat.get("cells"))
    dim = len(cells)
    if not 1 <= dim <= 3:
        raise ConfigError(f"cells has {dim} entries: give 1, 2 or 3 cell counts")
    if min(cells) < 2:
        raise ConfigError(f"cells = {list(cells)}: every axis needs at least 2 cells")
    if INIT_AXES.get(ic_name, dim) != dim:
        fit = [k for k in initial.REGISTRY if INIT_AXES.get(k, dim) == dim]
        raise ConfigError(f"cells = {list(cells)}: initial condition '{ic_name}' is {INIT_AXES[ic_name]}D, "
                          f"give {INIT_AXES[ic_name]} cell counts (in {dim}D use one of {', '.join(fit)})")
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
        Key("real", "", **PPC_LIMITS).check("reservoir_ppc", r)
    return GridKeys(cells, lengths, boundary, reservoir, _potential(flat.get("potential", ""), dim))


def _potential(value: Any, dim: int) -> Potential | None:
    """The potential, parsed: here, once (a scene's own, from :meth:`Scene.flat`, is taken as it is
    on a grid of its dimension, and parsed again from its source on another)."""
    if isinstance(value, Potential):
        if value.dim == dim:
            return value
        value = value.function if value.function is not None else value.source
    if isinstance(value, (int, float)) and not isinstance(value, bool):  # --set potential=3: a constant
        value = repr(value)
    if not (isinstance(value, str) or callable(value)):
        raise ConfigError(f"potential = {value!r}: give a formula in x, y, z in quotes")
    try:
        return Potential.of(value, dim)
    except ExprError as exc:
        raise ConfigError(f"potential = {quoted(value)}: {exc}") from None


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
    # times past t_end (say after --t-end shortened a run) are dropped, with a word; t_end is always written
    past = sorted({t for t in outs if t > t_end})
    if past:
        warnings.warn(f"output_times {', '.join(f'{t:g}' for t in past[:4])}{' …' * (len(past) > 4)} lie past "
                      f"t_end = {t_end:g}: no row is written for them", InputWarning, stacklevel=4)
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
    if h.tile > max(cells := scene.grid.cells):
        raise ConfigError(f"tile = {h.tile} > {max(cells)}, the grid's largest side: give at most {max(cells)}")
    if m.name == "hybrid" and 32 - math.ceil(math.log2(math.prod(n + 2 for n in cells))) < ID_BITS_MIN:
        raise ConfigError(f"cells = {list(cells)}: too many cells for the hybrid's 32-bit particle ids; "
                          f"use at most about {2 ** (32 - ID_BITS_MIN):.3g} cells")


MIN_VOLUME = 1e-60  # cell volumes in [1e-60, 1e60]: densities up to 1e15 / 1e-60, raised to the 4th power, fit
MAX_NESTING = 3  # lists in lists: [[lo, hi], ...] per side is the deepest any key takes


def _plain(key_: str, value: Any, depth: int = 0) -> Any:
    """Python callers' tuples as lists and NumPy scalars as Python numbers, as TOML gives them;
    lists nested deeper than any key takes refused."""
    if isinstance(value, (list, tuple)):
        if depth >= MAX_NESTING:
            raise ConfigError(f"{key_}: lists nested more than {MAX_NESTING} deep; give a number, a list or a list "
                              "of [lo, hi] pairs")
        return [_plain(key_, v, depth + 1) for v in value]
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
    if not MIN_VOLUME <= vol <= 1 / MIN_VOLUME:  # the density's fourth moments (kurtosis) in double precision
        raise ConfigError(f"lengths = {list(scene.grid.lengths)}: a cell's volume {vol:.3g} lies outside "
                          f"[{MIN_VOLUME:g}, {1 / MIN_VOLUME:g}], where the fourth moments of the density (particles "
                          "per unit volume) under- or overflow double precision; give lengths nearer 1")
    steps = scene.time.t_end / scene.dt
    if steps < 1 - 1e-9:  # (round-off: t_end = dt is one step)
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
    except (ValueError, RecursionError) as exc:  # thousands of digits, lists thousands deep
        raise ConfigError(f"--set {key_}: the value is out of reach ({_beyond(exc)}); give a plain number, "
                          "text or list") from None


def _beyond(exc: Exception) -> str:
    """What a parser's ValueError or RecursionError says, in a few words."""
    return "nested too deep" if isinstance(exc, RecursionError) else str(exc).split(":")[0].split(";")[0]


FLAGS = {"method": "--method", "ensemble": "--ensemble", "seed": "--seed", "t_end": "--t-end"}  # keys with a flag


def command_overrides(sets: list[str], flags: dict[str, Any]) -> dict[str, Any]:
    """The scene keys a command line sets: each ``--set KEY=VALUE`` and each flag of :data:`FLAGS`
    given (not None); a key given twice, by two ``--set`` or by ``--set`` and its flag, is refused."""
    overrides: dict[str, Any] = {}
    for item in sets:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"--set {item[:60]!r}: write KEY=VALUE, e.g. --set C=0.05")
        if key in overrides:
            raise ConfigError(f"--set {key} is given twice: give each key once")
        overrides[key] = parse_value(value.strip(), key)
    for key, value in flags.items():
        if value is None:
            continue
        if key in overrides:
            raise ConfigError(f"{key} is given twice, as {FLAGS[key]} {value} and as --set {key}=...: give it once")
        overrides[key] = value
    return overrides
