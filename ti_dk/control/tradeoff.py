"""The speed/accuracy trade on a user's own scene: a pilot of candidate settings against the particle
method, the bias of every per-cell moment with its standard error, cost against error, and the
cheapest setting that meets a named error (``python -m ti_dk.tradeoff``, :func:`tradeoff`).

The pilot keeps the scene's grid and physics and shrinks the ensemble (and, if asked, the horizon);
every candidate runs with the same members count, the reference with another seed. Each row's
samples are scored by :mod:`ti_dk.core.bias` over the cells asked for (default: every output time
after 0, the cells where the reference's mean lies between ``above`` and ``below`` particles). The
cost of a setting is its pilot's stepping time (compilation and set-up apart) scaled to the planned
ensemble and the full horizon by the work estimates (:func:`ti_dk.scene.estimates.work_estimate`:
their per-step overhead and per-member work, at this machine's measured speed). The error of a
setting is its worst moment's summary: in standard errors of a run of the planned ensemble (``z``),
or relative (``rel``). Two settings whose errors lie within 2 standard errors of their difference
are not told apart: the cheaper one dominates on the Pareto front, and the pick says which others it
cannot tell from.
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import controller
from ..core import bias
from ..output import tradeoff as write
from ..scene.estimates import work_estimate
from ..scene.load import command_overrides, load_scene, make_scene
from ..core.errors import ConfigError
from ..scene.schema import Scene

REFERENCE = "particle"
BUDGET = 120.0  # seconds the pilot may take by the work estimates, when its ensemble is not given
BELOW = 10.0  # default: the cells whose reference mean is below this many particles
ABOVE = 0.5  # and above this many: emptier cells hold too few particles for a pilot to see (and then
# a 10x larger pilot scores cells the smaller one could not, measured: fv on void1d read 12.7 SE, then 28)
MIN_PILOT = 40  # members


@dataclass(frozen=True)
class Candidate:
    """A setting tried: its label and the scene keys it changes (flat names)."""

    label: str
    overrides: dict = field(default_factory=dict)

    @classmethod
    def parse(cls, text: str) -> "Candidate":
        """``"KEY=VALUE KEY=VALUE ..."`` (as ``--set`` takes them) as a candidate labelled by that text."""
        return cls(" ".join(text.split()), command_overrides(text.split(), {}))


def candidates(scene: Scene) -> list[Candidate]:
    """The default set for ``scene``: fv and gaussian; the hybrid at the scene's threshold, half
    and twice it, a wider buffer, twice C with two particle sub-steps, f32, and where the region
    moves, tagged from each member's own density; fv at C halved and doubled, and f32."""
    h, C = scene.hybrid, scene.time.C
    hyb = {"method": "hybrid"}
    s = [Candidate("fv", {"method": "fv"}), Candidate("gaussian", {"method": "gaussian"}),
         Candidate("fv f32", {"method": "fv", "precision": "f32"}),
         Candidate(f"fv C={C / 2:g}", {"method": "fv", "C": C / 2}),
         Candidate(f"fv C={2 * C:g}", {"method": "fv", "C": 2 * C})]
    s += [Candidate(f"hybrid threshold {t:g}", hyb | {"threshold": t}) for t in (h.threshold / 2, h.threshold,
                                                                                  2 * h.threshold)]
    s += [Candidate(f"hybrid buffer {h.buffer + 2}", hyb | {"buffer": h.buffer + 2}),
          Candidate(f"hybrid C={2 * C:g} substeps 2", hyb | {"C": 2 * C, "particle_substeps": 2}),
          Candidate("hybrid f32", hyb | {"precision": "f32"})]
    if h.regrid_interval:  # a region that moves: from the other source
        other = "member" if h.region_from == "mean" else "mean"
        s.append(Candidate(f"hybrid region_from {other}", hyb | {"region_from": other}))
    return s


@dataclass
class Tradeoff:
    """What :func:`tradeoff` found: one dict per setting (``label``, ``overrides``, ``cost``,
    ``wall``, ``summaries`` {(moment, summary): (value, low, high)}, ``error``, ``pareto``,
    ``meets``, ``same_as``), the pick (a label, or None without a target) and its full-size scene."""

    rows: list[dict]
    planned: int
    pilot: Scene
    measure: str  # "z" or "rel"
    target: float | None
    pick: str | None
    pick_scene: Scene | None
    cells: np.ndarray  # the scored (row, cell) mask
    times: np.ndarray  # the pilot's row times
    maps: dict = field(repr=False, default_factory=dict)  # per setting: per-cell bias and SE

    def report(self) -> str:
        """The table and the answer, as printed."""
        unit = "in SEs of a run of" if self.measure == "z" else "relative, at"
        lines = [f"bias against the particle method, {unit} {self.planned:,} members (worst moment = error; "
                 f"[one-SE band]; {int(self.cells.sum()):,} cell-times scored):", write.table(self.rows, self.measure)]
        if self.target is not None:
            lines.append(self.answer())
        return "\n".join(lines)

    def answer(self) -> str:
        """The pick against the target, as printed: its cost and error (the particle method where
        no setting meets it), a doubt the pilot's uncertainty leaves, cheaper settings that might
        meet it too, and those the pilot cannot tell from it."""
        row = next(r for r in self.rows if r["label"] == self.pick)
        what = f"error ≤ {self.target:g}" + (" SE" if self.measure == "z" else " (relative)")
        if self.pick == REFERENCE:
            text = f"no candidate meets {what} at {self.planned:,} members: use the particle method (the reference)"
        else:
            e = row["error"]
            text = (f"pick: {self.pick} (cost {row['cost']:.3g} s, error {e[0]:.3g} [{e[1]:.3g}–{e[2]:.3g}]) "
                    f"meets {what} at {self.planned:,} members")
            if e[2] > self.target:
                text += "; within the pilot's uncertainty it might not: a larger --pilot-ensemble would say"
        maybe = [r for r in self.rows if not r["meets"] and r["error"][1] <= self.target and r["cost"] < row["cost"]]
        if maybe:
            text += ("\ncheaper, and within the pilot's uncertainty they might meet it too (a larger --pilot-ensemble "
                     "would say): " + ", ".join(f"{r['label']} ({r['error'][0]:.3g} [{r['error'][1]:.3g}–"
                                                f"{r['error'][2]:.3g}], {r['cost']:.3g} s)" for r in maybe))
        if row["same_as"]:
            text += f"\nthe pilot cannot tell its error from: {', '.join(row['same_as'])}"
        return text


def tradeoff(scene: Scene | str, *, planned: int | None = None, accuracy: float | None = None,
             rel_error: float | None = None, tries: list[Candidate] | None = None, defaults: bool = True,
             pilot_ensemble: int | None = None, pilot_t_end: float | None = None, below: float = BELOW,
             above: float = ABOVE, times: list[float] | None = None, budget: float = BUDGET,
             progress: bool | None = None, out: str | Path | None = None) -> Tradeoff:
    """Run the pilot of ``scene`` and score every setting against the particle method.

    Parameters
    ----------
    scene : Scene or str or Path
        The scene (from :func:`ti_dk.load_scene`), or a scene name or path.
    planned : int, optional
        The ensemble the user will run (default: the scene's); errors are in its standard errors.
    accuracy, rel_error : float, optional
        The error to meet: in standard errors at ``planned``, or relative (one of them).
    tries : list of Candidate, optional
        Settings of one's own (``Candidate.parse("method=hybrid threshold=3")``); ``defaults=False``
        runs only those (and the particles).
    pilot_ensemble : int, optional
        Members of the pilot (default: what fits ``budget`` seconds by the work estimates).
    pilot_t_end : float, optional
        A shorter horizon for the pilot (output times past it dropped).
    above, below : float
        The cells scored: the reference's mean between these, in particles per cell.
    times : list of float, optional
        The output times scored (default: all after 0).
    progress : bool, optional
        A progress bar on stderr (default: when stderr is a terminal).
    out : str or Path, optional
        Where to write ``tradeoff.csv``, ``tradeoff.h5``, ``tradeoff.png`` and, with a target,
        ``<scene>_pick.toml``.

    Returns
    -------
    Tradeoff
        The rows, the pick and its full-size scene; ``report()`` is the printed table and answer.

    Raises
    ------
    ConfigError
        With one line saying what to change.
    """
    scene = load_scene(scene) if isinstance(scene, (str, Path)) else scene
    planned, target = planned or scene.method.ensemble, _target(accuracy, rel_error)
    sets = [Candidate(REFERENCE, {"method": REFERENCE, "precision": "f64"})]
    sets += [c for c in (candidates(scene) if defaults else []) + list(tries or []) if c.label != REFERENCE]
    pilot = _pilot(scene, sets, pilot_ensemble, pilot_t_end, budget, planned)
    scenes = [make_scene(pilot.flat() | c.overrides | ({"seed": pilot.method.seed + 1} if i == 0 else {}))
              for i, c in enumerate(sets)]
    _announce(scenes)
    show = sys.stderr.isatty() if progress is None else progress
    rows, maps, cells, row_times = _measure(sets, scenes, scene, pilot, planned, (above, below, times), show)
    measure = "z" if rel_error is None else "rel"
    result = _judge(rows, planned, pilot, measure, target, scene, cells, row_times, maps)
    if out is not None:
        _write(result, Path(out), scene)
    return result


def _target(accuracy: float | None, rel_error: float | None) -> float | None:
    """The error to meet (one of the two, above 0), or None."""
    if accuracy is not None and rel_error is not None:
        raise ConfigError("give --accuracy or --rel-error, not both")
    target = accuracy if rel_error is None else rel_error
    if target is not None and not target > 0:
        raise ConfigError(f"the error to meet must be above 0 (got {target})")
    return target


def _measure(sets: list[Candidate], scenes: list[Scene], scene: Scene, pilot: Scene, planned: int, where: tuple,
             show: bool) -> tuple[list[dict], dict, np.ndarray, np.ndarray]:
    """Run every setting of the pilot (the reference first) and score it: its rows, its per-cell
    maps, the (row, cell) mask scored (``where``: above, below, times) and the rows' times."""
    rows, maps, ref = [], {}, None
    with tqdm(total=len(sets), unit="setting", disable=not show, file=sys.stderr) as bar:
        for c, sc in zip(sets, scenes):
            bar.set_description(c.label)
            res = controller.run(sc, progress=False, samples=True)
            ens = bias.Ensemble([s * sc.grid.cell_volume for s in res.samples])
            if ref is None:
                ref, cells = ens, _cells(ens, res.times, *where)
            ok = bias.usable(ref, [ens], cells)
            rows.append(_row(c, res, scene, pilot, planned, bias.compare(ens, ref, planned, ok)))
            maps[c.label] = {f"{k}_{p}": (ens.whole[0][k] - ref.whole[0][k]) if p == "bias" else
                             np.hypot(ens.whole[1][k], ref.whole[1][k]) for k in bias.MOMENTS for p in ("bias", "se")}
            bar.update()
    return rows, maps, cells, res.times


def _pilot(scene: Scene, sets: list[Candidate], members: int | None, t_end: float | None, budget: float,
           planned: int) -> Scene:
    """The pilot scene: the same grid and physics, ``members`` (or what fits ``budget``, at most
    ``planned``), a horizon
    of ``t_end`` (output times past it dropped; none left: t_end itself), nothing run alongside."""
    keys = {"compare": None}
    if t_end is not None:
        if scene.stats.t_equil is not None and t_end <= scene.stats.t_equil:
            raise ConfigError(f"--pilot-t-end {t_end:g}: a stationary scene needs it after t_equil = "
                              f"{scene.stats.t_equil:g}")
        kept = [t for t in scene.stats.output_times if t <= t_end * (1 + 1e-9)]
        keys |= {"t_end": t_end, "output_times": kept or [t_end]}
    if members is None:  # the estimates are linear in the members: a fixed part and a part per member
        one, two = (sum(work_estimate(make_scene(scene.flat() | keys | c.overrides | {"ensemble": m}))[1] for c in sets)
                    for m in (1, 2))
        members = max(MIN_PILOT, min(planned, 2 * int((budget - 2 * one + two) / max(two - one, 1e-12) / 2)))
    if members < 4:
        raise ConfigError(f"--pilot-ensemble {members}: a pilot needs at least 4 members (20 or more to be of use)")
    return make_scene(scene.flat() | keys | {"ensemble": members})


def _announce(scenes: list[Scene]) -> None:
    sc = scenes[0]
    seconds = sum(work_estimate(s)[1] for s in scenes)
    print(f"ti_dk: the pilot: {len(scenes)} settings of {sc.method.ensemble:,} members to t = {sc.time.t_end:g} "
          f"({sc.n_steps:,} steps at the scene's C): about {seconds / 60:.2g} min on 2 CPU cores by the work "
          f"estimates, plus a few seconds of compilation each", file=sys.stderr)


def _cells(ref: bias.Ensemble, row_times: np.ndarray, above: float, below: float,
           times: list[float] | None) -> np.ndarray:
    """The (row, cell) mask scored: the rows at ``times`` (default: every one after t = 0), the
    cells where the reference's mean lies between ``above`` and ``below`` particles."""
    rows = row_times > 0 if times is None else np.array([any(math.isclose(t, x, rel_tol=1e-6, abs_tol=1e-12)
                                                             for x in times) for t in row_times])
    if times is not None and rows.sum() < len(times):
        raise ConfigError(f"--times: the pilot's output times are {', '.join(f'{t:g}' for t in row_times)}; "
                          "name some of those")
    shape = (-1,) + (1,) * (ref.whole[0]["mean"].ndim - 1)
    mean = ref.whole[0]["mean"]
    cells = bias.usable(ref, [], rows.reshape(shape) & (mean < below) & (mean > above))
    if not cells.any():
        raise ConfigError(f"no cell of the scored rows has a mean between {above:g} and {below:g} particles: "
                          "lower --above or raise --below")
    return cells


def _row(c: Candidate, res, scene: Scene, pilot: Scene, planned: int, summaries: dict) -> dict:
    steady = res.wall_time - res.timing.get("setup", 0.0) - res.timing.get("compile", 0.0)
    full = make_scene(scene.flat() | c.overrides | {"compare": None, "ensemble": planned})
    cost = steady * work_estimate(full)[1] / work_estimate(res.scene)[1]  # the estimate's model, this machine's speed
    return {"label": c.label, "overrides": c.overrides, "cost": cost, "wall": res.wall_time,
            "squares": summaries, "summaries": {key: bias.root(*v) for key, v in summaries.items()},
            "negative_cells": int(np.max(res.diagnostics.get("negative_cells", [0]))), "scene": full}


def _judge(rows, planned, pilot, measure, target, scene, cells, times, maps) -> Tradeoff:
    """Each row's error (its worst moment), the Pareto front, whether it meets ``target``, the
    settings the pilot cannot tell it from, and the pick."""
    for r in rows:
        worst = max(bias.MOMENTS, key=lambda k: r["summaries"][k, measure][0])
        r["error"], r["worst"] = r["summaries"][worst, measure], r["squares"][worst, measure]
        r["meets"] = None if target is None else bool(r["error"][0] <= target)
        r["sure"] = target is None or not r["error"][1] <= target < r["error"][2]  # the band does not span it
    for r in rows:
        r["same_as"] = [o["label"] for o in rows if o is not r and not bias.differ(r["worst"], o["worst"])]
        r["pareto"] = not any(_dominates(o, r) for o in rows if o is not r)
    pick = None
    if target is not None:
        pick = min((r for r in rows if r["meets"]), key=lambda r: r["cost"])["label"]
    pick_scene = None
    if pick is not None:
        full = next(r for r in rows if r["label"] == pick)["scene"]
        pick_scene = make_scene(full.flat() | {"ensemble": planned, "name": f"{scene.name}_pick"})
    return Tradeoff(rows, planned, pilot, measure, target, pick, pick_scene, cells, times, maps)


def _dominates(a: dict, b: dict) -> bool:
    """``a`` is cheaper than ``b`` and no worse, or as cheap and better (errors the pilot cannot
    tell apart count as equal)."""
    same = not bias.differ(a["worst"], b["worst"])
    better = a["error"][0] < b["error"][0] and not same
    return (a["cost"] < b["cost"] and (same or better)) or (a["cost"] <= b["cost"] and better)


def _write(result: Tradeoff, out: Path, scene: Scene) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write.write_csv(out / "tradeoff.csv", result.rows)
    attrs = {"scene": scene.name, "planned_ensemble": result.planned, "pilot_ensemble": result.pilot.method.ensemble,
             "pilot_t_end": result.pilot.time.t_end, "measure": result.measure, "times": result.times,
             "target": np.nan if result.target is None else result.target, "pick": result.pick or ""}
    write.write_h5(out / "tradeoff.h5", result.rows, attrs, result.maps, result.cells)
    unit = "error: worst moment's RMS bias " + ("in SEs of a run of" if result.measure == "z" else "relative, at")
    write.plot(out / "tradeoff.png", result.rows,
               f"{scene.name}: pilot of {result.pilot.method.ensemble:,} members against particles",
               f"{unit} {result.planned:,} members", result.target, result.pick)
    if result.pick_scene is not None:
        comment = (f"ti_dk.tradeoff's pick for {scene.name}: {result.pick}\n{result.answer()}\n"
                   f"run it as it is: python -m ti_dk.scene {out / (scene.name + '_pick.toml')}")
        (out / f"{scene.name}_pick.toml").write_text(write.scene_toml(result.pick_scene, comment))
