"""The AMAR hybrid (paper §3): the SPDE everywhere, real Brownian particles in a particle region;
the solver, its state and its step order."""

import time

import numpy as np
import taichi as ti

from .. import pools
from ..methods.fv import SPDESolver
from ..methods.particles import Walker
from ..methods.records import Scalars
from ..methods.solver import RegionSolver
from . import clustering
from .ghosts import Sampler
from .region import Region
from .regridder import Regridder
from .sync import Coupling


def _laps(timing: dict[str, float], weight: int):
    """A stopwatch over one step: each ``lap(part)`` adds to ``timing[part]`` ``weight`` times the
    seconds since the last lap (or since the stopwatch was made), read after the device has
    finished what was launched (kernels may run asynchronously). With ``weight`` 0 it neither
    syncs nor times: a step on a GPU, where every sync stalls the launches that would overlap."""
    if weight:
        ti.sync()
    last = time.perf_counter()

    def lap(part: str) -> None:
        nonlocal last
        if weight:
            ti.sync()
            now = time.perf_counter()
            timing[part] += weight * (now - last)
            last = now

    return lap


class HybridSolver(RegionSolver):
    r"""SPDE on the whole grid coupled to particles in a region (paper §3.1–3.2).

    One step ``n → n+1`` runs the paper's three stages: a regrid when one is due
    (:meth:`Regridder.when_due`); the ghost ring filled and the SPDE advanced; the particle
    sub-steps and the synchronisation. In detail:

    1. the ghost ring (cells outside the region within Chebyshev distance 1 of it, and Dirichlet
       reservoir cells beyond covered boundary cells) gets ``ℓ`` particles plus one with
       probability ``α``, where ``ℓ + α = max(q_I^n, 0) V_c`` (paper §3), placed with the linear
       profile of :meth:`InCell.tilt` (:mod:`.incell`) (the slope of the deterministic q̄, by default);
    2. the SPDE advances everywhere, eq. (9), giving ``q^{n+1,*}`` and the face fluxes ``F``;
    3. every particle (real and ghost) takes one clamped step (:class:`Walker`; a ghost's step is
       drawn as it is sampled in 1, and only the ghosts that enter are stored); those ending in
       the region are kept, the rest dropped, and the net crossings are counted per uncovered
       cell: ``ΔN_I`` gains 1 for each real particle that leaves into ``I`` and loses 1 for each
       ghost from ``I`` that enters. With ``particle_substeps = k`` (end of paper §3.1) this is
       done k times with steps of Δt/k, the ghosts of sub-step s sampled afresh from
       ``(1 − s/k) q^n + (s/k) q^{n+1,*}`` and ΔN summed over the sub-steps;
    4. synchronisation (eq. 12 and its multi-dimensional form): covered cells take
       ``q_I = N_I / V_c``; each uncovered ring cell drops the SPDE fluxes it exchanged with covered
       face neighbours (set S1) and takes the particle crossings (set S2),

       .. math:: q_I^{n+1} = q_I^{n+1,*} - \frac{1}{V_c}\sum_{i∈S_1} Δt A_a F^{i→I}
                 + \frac{ΔN_I}{V_c}.

    The region is a cell mask per member (:class:`Region`), so the result does not depend on how
    it is cut into boxes, and a particle's random numbers depend only on its identity (birth
    cell, index, birth step), never on its slot. With a fixed region and periodic or Neumann
    walls, the total number of particles (SPDE mass plus particles) is conserved to round-off.

    The solver is made of parts: the region (:class:`Region`), the sampling of ghosts and newly
    covered cells (:class:`Sampler`), the walk and synchronisation (:class:`Coupling`), and the
    regrids, scheduled and on demand (:class:`Regridder`, which moves the particles to a new
    region); the particles lie in a pool (:mod:`ti_dk.pools`).

    Parameters
    ----------
    spde : SPDESolver
        The SPDE on the whole grid (built with ``track_mean`` for the ghosts' q̄ profile).
    params : RegridParams
        The region's parameters (:class:`~.clustering.RegridParams`).
    regrid_interval : int
        Steps between scheduled regrids (0: the first region is kept).
    ghost_profile : str
        The in-cell profile of sampled particles (:class:`~.incell.InCell`).
    substeps : int
        Particle sub-steps per SPDE step.
    pool_layout : str
        Where the particles are stored: ``flat`` or ``pointer`` (:data:`ti_dk.pools.LAYOUTS`).
    slots : int
        Slots per member a flat pool plans for (:func:`~ti_dk.scene.estimates.hybrid_slots`), made
        when the first region is (more, if that region needs more).
    """

    def __init__(self, spde: SPDESolver, params: clustering.RegridParams, regrid_interval: int,
                 ghost_profile: str = "mean", substeps: int = 1, pool_layout: str = "flat", slots: int = 1):
        grid = spde.grid
        self.profile, self.substeps = ghost_profile, substeps
        self.spde, self.grid, self.dt, self.ensemble, self.real = spde, grid, spde.dt, spde.ensemble, spde.real
        self.dim, self.n = grid.dim, grid.cells
        # one particle sub-step; each particle makes its own Philox call (its slots are not in identity order)
        self.walker = Walker(grid, spde.dt / substeps, spde.real, spde.key, spde.member0, alone=True)
        self.regions = Region(grid, self.ensemble, params)
        spde.replaced_in(self.regions.covered)  # covered cells take their counts at each sync (step 4)
        self.sampler = Sampler(spde, self.regions, self.walker, ghost_profile, substeps)
        self.coupling = Coupling(spde, self.regions, self.sampler, self.walker)
        c = self.coupling
        # the SPDE's diagnostics and the coupling's, read together
        self.scalars = Scalars(spde.scalars.fields + [c.wall_inflow, c.p_inflow, c.clamped])
        self.pool = pools.make(pool_layout, grid, self.ensemble, self.real)  # flat or pointer (pools.LAYOUTS)
        self.slots = slots  # a flat pool's slots per member from the first region on (estimates.hybrid_slots)
        self.cur = 0  # the pool buffer holding the particles between steps
        self.regridder = Regridder(self, params, regrid_interval)  # the schedule, the regrids, their log
        self.timing = {"spde": 0.0, "particles": 0.0, "regrid": 0.0}  # seconds spent in each part
        # steps between two timed steps (their time × this is the estimate; step 0 is timed as it is):
        # each on the CPU, whose kernels run as they are launched; every 16th on a GPU, where syncs cost
        self.timed_every = 1 if ti.lang.impl.current_cfg().arch == ti.cpu else 16

    @property
    def regrids(self) -> list[dict]:
        """One record per regrid (:data:`~.regridder.REGRID_LOG`)."""
        return self.regridder.log

    @property
    def boxes(self) -> list[list[clustering.Box]]:
        """Each member's region as boxes."""
        return self.regions.boxes

    @property
    def n_cover(self) -> int:
        """Covered cells, all members."""
        return self.regions.n_cover

    @property
    def n_ring(self) -> int:
        """Ghost cells, all members."""
        return self.regions.n_ring

    @property
    def n_real(self):
        """Particles of each member between steps (a field)."""
        return self.pool.kept

    # -- public -------------------------------------------------------------------------
    def initialize(self) -> None:
        """The first region from the (already initialised) SPDE, particles sampled into it."""
        self.regrid(0)
        self.diagnose()

    def regrid(self, n: int) -> None:
        """A new region from the SPDE at step ``n`` (:meth:`Regridder.regrid`)."""
        self.regridder.regrid(n)

    def extend(self, n: int) -> None:
        """Cover, before step ``n``, the uncovered cells below ``threshold`` (:meth:`Regridder.extend`)."""
        self.regridder.extend(n)

    def set_region(self, masks: np.ndarray, n: int) -> None:
        """Make ``masks`` (``(ensemble, *cells)`` booleans) the particle region at step ``n``, between
        steps (:meth:`Regridder.set_region`)."""
        self.regridder.set_region(masks, n)

    def diagnose(self) -> None:
        """The SPDE's diagnostics (:meth:`SPDESolver.diagnose`) and, in the same pass, how many
        uncovered cells are below ``regrid_floor · threshold`` (:meth:`Regridder.count_low`), which
        the next step's extension check reads."""
        self.regridder.count_low(True)

    def step(self, n: int) -> None:
        """Advance from step ``n`` to ``n + 1`` in the paper's three stages (the class docstring's 1–4),
        the seconds of each part added to :attr:`timing`."""
        every = self.timed_every
        lap = _laps(self.timing, 1 if n == 0 else every if n % every == 0 else 0)  # step 0 (it compiles) as it is
        self.regridder.when_due(n)  # stage 1: the regrid, when due
        lap("regrid")
        if self.n_cover == 0:  # no particle region: a plain SPDE step
            self.spde.step(n)
            lap("spde")
            return
        if self.substeps > 1:  # stage 2: the ghosts filled from q^n, the SPDE advanced (steps 1, 2)
            self.sampler.q_old.copy_from(self.spde.q)
        self._fill_ghosts(n * self.substeps, 0.0, self.tilt_on(n))
        lap("particles")
        self.spde.advance(n)
        lap("spde")
        self._particle_steps(n)  # stage 3: the particle sub-steps and the synchronisation (steps 3, 4), diagnosed
        lap("particles")

    def _particle_steps(self, n: int) -> None:
        """Steps 3 and 4 after the SPDE's: S1, the k particle sub-steps of Δt/k (ghosts from q
        interpolated in time), the synchronisation with the last, and the diagnostics
        (:meth:`Coupling.cross`, which compacts a pool that compacts in place)."""
        c, k = self.coupling, self.substeps
        for s in range(k):
            if s > 0:
                self._fill_ghosts(n * k + s, s / k, 1)
            c.cross(self.pool, self.cur, n * k + s, int(s == 0), int(s == k - 1), self.n_ring, self.n_cover,
                    self.regridder.params.trigger)
            if not self.pool.in_place:
                self.compact()
        self.regridder.counted()

    def compact(self) -> None:
        """Keep the marked particles (in place, or in the other buffer: the pointer layout, which may
        need a larger pool)."""
        self.pool, self.cur = self.pool.compacted(self.cur)

    def tilt_on(self, n: int) -> int:
        """Whether particles sampled at step ``n`` are tilted: not at the start with ``mean``, where
        q̄ is the piecewise-constant initial condition (particles lie uniformly in each cell)."""
        return int(self.profile != "mean" or n > 0)

    def _fill_ghosts(self, sub: int, w: float, tilt_on: int) -> None:
        """Ghosts for particle sub-step ``sub`` from ``(1 − w) q^n + w q^{n+1,*}`` (for s > 0 after S1,
        :meth:`Coupling._s1`: what the SPDE left in the ghost cell); the fill is a pure
        function of its inputs, so a pool that is too small is grown and the fill redone."""
        while True:
            need = self.sampler.check_need(self.sampler.fill(self.pool, self.cur, sub, self.n_ring, w, tilt_on, 1))
            if need <= self.pool.capacity:
                return
            self.pool = self.pool.grown(2 * need)
            self.pool.truncate(self.cur)

    def state(self) -> dict[str, np.ndarray]:
        """SPDE fields, region, boxes, regrid log and the particles (compacted, with their ids)."""
        x, pid, n = self.pool.occupied(self.cur)
        region = self.regions.state()
        st = {f"spde_{k}": v for k, v in self.spde.state().items()}
        st |= {"covered": region["covered"], "n_real": n, "x": x, "pid": pid, "boxes": region["boxes"]}
        return st | self.regridder.state()

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """A state of :meth:`state` back (a restart continues bit for bit)."""
        self.spde.load_state({k[5:]: v for k, v in st.items() if k.startswith("spde_")})
        self.regions.load_state(st)
        self.pool = self.pool.restored(st["x"], st["pid"], st["n_real"], self.regions.grown(self.regions.mask()))
        self.cur = 0
        self.regridder.load_state(st)

    def density(self) -> np.ndarray:
        """The composite density ``(ensemble, *cells)`` [particles / volume]: the SPDE's, whose covered
        cells hold their particle counts since the last synchronisation."""
        return self.spde.density()

    def region(self) -> np.ndarray:
        """The particle region of every member, ``(ensemble, *cells)`` booleans."""
        return self.regions.mask()

    def content(self) -> tuple:
        """The SPDE's ``q`` (covered cells hold their counts), ``V_c``, the covered mask."""
        return self.spde.q, self.grid.cell_volume, self.regions.covered

    def diagnostics(self) -> dict[str, float]:
        """The SPDE's diagnostics of the last step, with the particles' inflow at walls and
        reservoirs, clamped steps, the particle count and the last regrid's change of the total."""
        values = self.scalars.read()  # one read, not two
        k = self.spde.scalars.count
        d = self.spde.diagnostics(values[:k])
        if self.n_cover:  # otherwise the last step was a plain SPDE step
            wall, injected, clamped = values[k:]
            d["boundary_inflow"] = d["boundary_inflow"] + float(wall) + int(injected)
            d["clamped_steps"] = int(clamped)
        d["particles"] = pools.total(self.pool.kept)
        d["regrid_change"] = self.regridder.change
        return d
