"""What only the whole scene can say about its initial density, its potential and its hybrid's
sizes, checked by :func:`ti_dk.scene.load.make_scene` after every key has its kind and limits:
a density no particle count can hold, a potential the methods would read two ways (a jump or
kink the particle walk cannot see; a jump at a periodic seam), a time step beyond the scheme's
stability, sizes beyond the grid, and keys that do nothing for this scene (said, not refused)."""
from __future__ import annotations

import math
import warnings

import numpy as np

from ..core.errors import ConfigError, ExprError, InitError
from ..core.expr import functions_used, numpy_value, quoted
from .schema import CLAMP_WARN, MAX_PPC, ClampWarning, Scene
from ..core.grid import Grid
from ..hybrid.ghosts import HYBRID_STEP_LIMIT
from ..methods.fluxes import drift_coefficients, stability_number

WALKERS = ("particle", "hybrid")  # methods that move particles by the drift −½∇U, so need U's gradient
KINKS = ("step", "abs")  # functions of the formula language with a jump or a kink: no gradient there
COMPUTED = {"expression": "density", "array": "density_file", "boltzmann": "potential"}  # initial densities
# that only these keys bound (the others are in range by their own keys' limits)
PERIODIC_TOL = 1e-6  # relative difference of U at a periodic axis's two ends taken as the same value


class InputWarning(UserWarning):
    """Input that is taken, but not all of it (output times past t_end), or that does nothing here."""


def check_initial(scene: Scene) -> np.ndarray:
    """The initial density in particles per cell, refused unless finite, >= 0 and at most
    :data:`MAX_PPC` in every cell (only a formula, a file or a potential can break that; a file is
    read again at every run, so it is checked again there)."""
    key_ = COMPUTED.get(scene.init.name, "init")
    try:
        ppc = scene.initial_ppc
    except Exception as exc:  # ours say what to change; a callable potential's own error what failed
        known = isinstance(exc, (ExprError, InitError))
        raise ConfigError(f"{key_}: " + (str(exc) if known else f"evaluating it failed ({type(exc).__name__}: {exc})")) from None
    ok = np.isfinite(ppc) & (ppc >= 0) & (ppc <= MAX_PPC)
    if not np.all(ok):
        bad = np.argwhere(~ok)[0].tolist()
        raise ConfigError(f"{key_}: the initial density is {ppc[tuple(bad)]:.4g} in cell {bad}: "
                          f"give finite densities in [0, {MAX_PPC:g}] particles per cell in "
                          "every cell (no particle count beyond that is exact in double precision)")
    return ppc
def _drift(scene: Scene) -> tuple[float, float]:
    """With a potential: the FV scheme's stability number (:func:`fluxes.stability_number`, from the
    Scharfetter–Gummel weights the solver will read: made once, :func:`fluxes.drift_coefficients`) and
    the largest chance that a particle step along an axis is clamped, its drift −½∂_aU Δt
    evaluated at the cell centres; a potential that is not finite where the run reads it is refused."""
    grid, pot = Grid.from_scene(scene), scene.potential
    try:
        coef = drift_coefficients(grid)
        centres = np.meshgrid(*((np.arange(n) + 0.5) * h for n, h in zip(grid.cells, grid.dx)), indexing="ij")
        u = pot(*centres)
        grads = [np.asarray(np.gradient(u, h, axis=a)) for a, h in enumerate(grid.dx)] if pot.tree is None else \
            [np.broadcast_to(numpy_value(t, tuple(centres)), u.shape) for t in pot.gradient_trees()]
    except Exception as exc:
        raise ConfigError(f"potential = {quoted(pot.source)}: evaluating it failed ({type(exc).__name__}: {exc})") from None
    if not (np.all(np.isfinite(coef)) and np.all(np.isfinite(u)) and all(np.all(np.isfinite(g)) for g in grads)):
        raise ConfigError(f"potential = {quoted(pot.source)} is not finite everywhere on the grid (or in a reservoir "
                          "cell): give a potential finite on the closed domain")
    dt = scene.dt / (scene.hybrid.particle_substeps if scene.method.name == "hybrid" else 1)  # a particle step
    sd, clamp = math.sqrt(dt), 0.0
    for g, h in zip(grads, grid.dx):
        mu = 0.5 * float(np.max(np.abs(g))) * dt
        clamp = max(clamp, 0.5 * (math.erfc((h - mu) / (sd * math.sqrt(2))) + math.erfc((h + mu) / (sd * math.sqrt(2)))))
    return stability_number(grid, scene.dt), clamp


def stability_limit(scene: Scene) -> float:
    """The explicit FV scheme's limit on C on the scene's grid, with its potential: stable below it."""
    return scene.time.C / (stability_number(scene.grid, scene.dt) if scene.potential is None else _drift(scene)[0])


def check_time_step(scene: Scene) -> None:
    """Refuse a time step past the explicit stability limit (with the drift of a potential, the
    Scharfetter–Gummel number), unless ``allow_unstable``, naming the limit and the C to use; refuse
    a hybrid run past the particle births' 27-bit numbering; warn (``ClampWarning``) where a particle
    step is clamped to ±Δx often."""
    number, clamp = (stability_number(scene.grid, scene.dt), scene.clamp_probability) if scene.potential is None \
        else _drift(scene)
    limit = scene.time.C / number
    if number >= 1 and not scene.time.allow_unstable and scene.method.name != "particle":
        raise ConfigError(
            f"C = {scene.time.C} is beyond the explicit stability limit C < {limit:.4g} of the FV scheme on this grid"
            f"{' with this potential' if scene.potential else ''}: "
            f"lower C (e.g. --set C={limit / 2:.4g}) or set allow_unstable=true for a stability experiment"
        )
    if scene.method.name == "hybrid" and scene.n_steps * scene.hybrid.particle_substeps >= HYBRID_STEP_LIMIT:
        raise ConfigError(
            f"t_end = {scene.time.t_end} is {scene.n_steps * scene.hybrid.particle_substeps:,} particle steps; "
            "the hybrid numbers "
            f"particle births in 27 bits: give fewer than {HYBRID_STEP_LIMIT:,} (shorter t_end, larger C or fewer "
            "particle_substeps)")
    if scene.method.name in ("particle", "hybrid") and clamp > CLAMP_WARN:
        warnings.warn(
            f"C = {scene.time.C}: a particle step is clamped to ±Δx with probability {clamp:.2g} "
            f"per axis and step (> {CLAMP_WARN:g}); lower C to make clamping rare",
            ClampWarning,
            stacklevel=3,
        )




def check_potential(scene: Scene) -> None:
    """A potential every method reads the same way: none with a jump or kink for a method that
    walks by its gradient, and, along a periodic axis, the same value at both ends."""
    pot = scene.potential
    if pot is None:
        return
    walkers = [m for m in (scene.method.name, scene.method.compare) if m in WALKERS]
    kinks = sorted(functions_used(pot.tree) & set(KINKS)) if pot.tree is not None else []
    if walkers and kinks:
        raise ConfigError(
            f"potential = {quoted(pot.source)}: {kinks[0]}() has a jump or kink where U has no gradient, and method "
            f"{walkers[0]} moves particles by the drift -grad(U)/2 alone, so it would not follow e^(-U) there as fv "
            "does; give a smooth potential (e.g. 20*(1+tanh((x-0.5)/0.02))/2 for a step) or use method fv or gaussian")
    g = scene.grid
    centres = [(np.arange(n) + 0.5) * (L / n) for n, L in zip(g.cells, g.lengths)]
    for a, (lo, _) in enumerate(g.boundary):
        if lo != "periodic":
            continue
        ends = [pot(*np.meshgrid(*(centres[:a] + [np.array([at])] + centres[a + 1:]), indexing="ij", sparse=True))
                for at in (0.0, g.lengths[a])]
        same = np.isclose(ends[0], ends[1], rtol=PERIODIC_TOL, atol=PERIODIC_TOL, equal_nan=True)
        if not np.all(same):
            i = tuple(np.argwhere(~same)[0])
            x = "xyz"[a]
            raise ConfigError(
                f"potential = {quoted(pot.source)} is not periodic along axis {a} ({x}), whose sides are periodic: U is "
                f"{ends[0][i]:.6g} at {x} = 0 but {ends[1][i]:.6g} at {x} = {g.lengths[a]:g} (a jump of "
                f"{ends[1][i] - ends[0][i]:.3g}); give a potential with the same value at both ends, or make the axis "
                "neumann or dirichlet")


def check_hybrid_sizes(scene: Scene) -> None:
    """The hybrid's sizes in cells, bounded by the grid (beyond it they mean nothing, and a buffer
    grows the region one cell at a time)."""
    most, h = max(scene.grid.cells), scene.hybrid
    for name, value in (("buffer", h.buffer), ("min_box", h.min_box)):
        if value > most:
            raise ConfigError(f"{name} = {value:,}: give at most {most}, the most cells along an axis of this grid")


def check_unused(scene: Scene) -> None:
    """Keys that do nothing for this scene, said in an :class:`InputWarning` each: a reservoir on a
    side that is not Dirichlet, and statistics from one sample (a stationary run pooling one step
    of one member: no variance; S(k) of one member without ``t_equil``: nothing to draw)."""
    def say(message: str) -> None:
        warnings.warn(message, InputWarning, stacklevel=5)  # the caller of load_scene

    g, st, E = scene.grid, scene.stats, scene.method.ensemble
    for a, (kinds, levels) in enumerate(zip(g.boundary, g.reservoir_ppc)):
        unused = [(side, kind, level) for side, kind, level in zip(("lower", "upper"), kinds, levels)
                  if level and kind != "dirichlet"]
        if unused:
            say(f"reservoir_ppc on axis {a} does nothing on its "
                + " and ".join(f"{side} side ({kind}, {level:g} given)" for side, kind, level in unused)
                + ": only dirichlet sides have a reservoir")
    if st.t_equil is not None and E == 1:
        samples = (scene.n_steps - round(st.t_equil / scene.dt)) // st.sample_every + 1
        if samples < 2:
            say(f"t_equil = {st.t_equil:g} with sample_every = {st.sample_every} pools one step of one member: the "
                "row's variance, skewness and kurtosis mean nothing; lower t_equil or sample_every, or raise ensemble")
    if st.structure_factor and E == 1 and st.t_equil is None:
        say("structure_factor = true with one member and no t_equil: every row is one sample, so S(k) is not "
            "defined and none is drawn; raise ensemble or set t_equil")
