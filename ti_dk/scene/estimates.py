"""What a scene needs before it runs: memory (fields, particles, statistics) and work (steps,
seconds), estimated from rates measured in ``benchmarks/RESULTS.md``; a scene that would not fit
the machine is refused."""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..core.grid import Grid
from ..hybrid import clustering
from ..pools import capacity
from .schema import ConfigError, Scene

# ---------------------------------------------------------------------------------------
# what a run needs: memory, steps, time
# ---------------------------------------------------------------------------------------
SPDE_RATE = {1: 1e8, 2: 2e7, 3: 2e7}  # cell-updates per second on 2 CPU cores, by dimension (RESULTS.md, rounded down)
PARTICLE_RATE = 3e7  # particle steps per second, likewise
HYBRID_PARTICLE_RATE = 1.5e7  # the hybrid's particle part (ghost fill, walk, cap, compaction) per particle-step
REGRID_RATE = 1e7  # grid cells per second a hybrid regrid or on-demand extension handles (host masks, lists)
# seconds every step costs whatever its size: its kernels' launches, the step loop and its handlers
# (void1d, 40 cells, one member: 0.6 ms fv, 1.3 ms hybrid, 0.1 ms particle per step; RESULTS.md)
STEP_OVERHEAD = {"fv": 5e-4, "gaussian": 5e-4, "hybrid": 1e-3, "particle": 1e-4}


def _particles(scene: Scene) -> float:
    """The particles per member the particle method must hold (an upper bound for huge grids)."""
    from ..methods.particles import ParticleSolver  # imported here: the particle method is needed only for its memory rule

    m = math.prod(scene.grid.cells)
    if m <= 10**7:
        return ParticleSolver.capacity_for(Grid.from_scene(scene), scene.initial_ppc)
    most = math.ceil(_ppc_max(scene)) * m  # every cell at the largest density
    return capacity(most) if Grid.from_scene(scene).has_dirichlet else most


def _ppc_max(scene: Scene) -> float:
    """The largest initial or reservoir density, in particles per cell."""
    ppc = [v for k, v in scene.init.params.items() if k.startswith("ppc")]
    if scene.init.name in ("expression", "array", "boltzmann"):  # no ppc key says it: the density does
        ppc.append(float(scene.initial_ppc.max()))
    return max(ppc + [Grid.from_scene(scene).reservoir_ppc_max])


def hybrid_slots(scene: Scene) -> int:
    """The slots per member the hybrid's flat pool is made with, at its first region (or a quarter
    more than that region needs, where more; :meth:`~ti_dk.pools.ParticlePool.grown`):
    :func:`~ti_dk.pools.capacity` of the threshold density (or the largest density, if lower) in
    every cell. A region holds the cells below the threshold and its buffer: this bounds it but
    for a buffer of dense cells around a region that fills much of the grid. A pool that grows is
    a new one, and the kernels that take it compile anew (seconds; rare, and amortised by
    doubling); planned so, the pool of ``ellipse2d`` never grows in its run (tested)."""
    return capacity(min(scene.hybrid.threshold, _ppc_max(scene)) * math.prod(scene.grid.cells))


def memory_estimate(scene: Scene) -> dict[str, float]:
    """Bytes a run needs, by part: solver fields, particles, host copies, statistics, histogram,
    structure factor.

    Rough (within a factor of about 2) but computed before anything is allocated; the hybrid's
    particle pool is counted as planned (:func:`hybrid_slots`).
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
            # two buffers of slots for every member, as planned (hybrid_slots), and a keep flag and a tail rank
            est["particles"] += scene.method.ensemble * hybrid_slots(scene) * (2 * (scene.grid.dim * real + 8) + 5)
        if method == "particle":
            est["fields"] += mc * 4
            # with reservoirs: ids (8 bytes), a keep flag and a tail rank (the pool compacts in place)
            d = Grid.from_scene(scene).has_dirichlet
            per_slot = scene.grid.dim * real + 13 * d
            est["particles"] += scene.method.ensemble * _particles(scene) * per_slot
    est["host copies"] = 3 * mc * 8  # density read back as float64, and its statistics update
    rows = 1 if scene.stats.t_equil is not None else len(scene.stats.output_times)
    est["statistics"] = (rows + 1) * cells * 12 * 8  # moments and accumulators per row
    if scene.stats.histogram:
        est["histogram"] = (rows + 1) * cells * (scene.stats.histogram[1] - scene.stats.histogram[0] + 1) * 8
    if scene.stats.structure_factor:  # the counts' transforms and their moments on the host; accumulators per row
        est["structure factor"] = 5 * mc * 8 + (rows + 1) * cells * 6 * 8
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
    steps. The rates are rounded down from ``benchmarks/RESULTS.md``, where the estimates are also
    compared with whole runs.
    """
    cells = math.prod(scene.grid.cells)
    mc = scene.method.ensemble * cells
    per_step = 0.0
    for method in (scene.method.name, scene.method.compare):
        per_step += STEP_OVERHEAD.get(method, 0.0)
        if method in ("fv", "gaussian", "hybrid"):
            per_step += mc / SPDE_RATE[scene.grid.dim]
        if method == "particle":
            per_step += scene.method.ensemble * _particles(scene) / PARTICLE_RATE
        if method == "hybrid":
            h = scene.hybrid
            tagged = int(np.count_nonzero(clustering.tag(scene.initial_ppc, h.threshold))) if cells <= 10**7 else cells
            held = h.threshold if h.regrid_interval else h.threshold / 2  # particles per tagged cell
            per_step += scene.method.ensemble * tagged * held / HYBRID_PARTICLE_RATE
            if h.regrid_interval:
                per_step += mc / REGRID_RATE / (1 if h.regrid_floor > 0 else h.regrid_interval)
    return scene.n_steps, scene.n_steps * per_step


