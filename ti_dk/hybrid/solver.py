"""The AMAR hybrid (paper §3): the SPDE everywhere, real Brownian particles in a particle region;
the solver, its state and its step order."""

import time

import numpy as np
import taichi as ti

from .. import pools
from ..methods.fv import SPDESolver
from ..methods.particles import Walker
from ..methods.solver import RegionSolver
from . import clustering
from .ghosts import Sampler
from .region import Region
from .regridding import REGRID_LOG, Regridding
from .sync import Coupling


def _clock() -> float:
    """Seconds, after the device has finished what was launched (kernels may run asynchronously)."""
    ti.sync()
    return time.perf_counter()


class HybridSolver(Regridding, RegionSolver):
    r"""SPDE on the whole grid coupled to particles in a region (paper §3.1–3.2).

    One step ``n → n+1``:

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

    Regridding (every ``regrid_interval`` steps, at the start, and on demand for a member that
    starts a step with an uncovered cell below ``regrid_floor · threshold``, see :meth:`extend`;
    0 keeps the first region): tag and
    buffer, then tiles flagged on the device with hysteresis (:mod:`.tiles`, the default) or
    Berger–Rigoutsos per member on the host (``region = "boxes"``); particles in cells that stay covered are kept, cells
    that leave the region keep their count as density, newly covered cells are sampled from the
    SPDE (the only step that changes the total; logged in ``regrids``). At the start the state is
    the piecewise-constant initial condition, so those particles lie uniformly in their cells.
    """

    def __init__(self, spde: SPDESolver, params: clustering.RegridParams, regrid_interval: int,
                 ghost_profile: str = "mean", substeps: int = 1, pool_layout: str = "flat"):
        grid = spde.grid
        self.profile, self.substeps = ghost_profile, substeps
        self.spde, self.params, self.regrid_interval = spde, params, regrid_interval
        self.grid, self.dt, self.ensemble, self.real = grid, spde.dt, spde.ensemble, spde.real
        self.dim, self.n = grid.dim, grid.cells
        self.walker = Walker(grid, spde.dt / substeps, spde.real, spde.key, spde.member0)  # one particle sub-step
        self.regions = Region(grid, self.ensemble, params)
        spde.replaced_in(self.regions.covered)  # covered cells take their counts at each sync (step 4)
        self.sampler = Sampler(spde, self.regions, self.walker, ghost_profile, substeps)
        self.coupling = Coupling(spde, self.regions, self.sampler, self.walker)
        self.pool = pools.make(pool_layout, grid, self.ensemble, self.real)  # flat or pointer (pools.LAYOUTS)
        self.cur = 0  # the pool buffer holding the particles between steps
        self.regrids: list[dict] = []  # one record per regrid
        self._change = 0.0  # created − removed at this step's regrid
        self._removed = 0.0  # SPDE content Σ q V_c of the cells the last regrid covered anew
        self._created = 0  # particles the last regrid sampled into them
        self.timing = {"spde": 0.0, "particles": 0.0, "regrid": 0.0}  # seconds spent in each part
        self._low: int | None = None  # uncovered cells below params.trigger at the last diagnose (None: not known)

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

    def diagnose(self) -> None:
        """The SPDE's diagnostics (:meth:`SPDESolver.diagnose`) and, in the same pass, how many
        uncovered cells are below ``regrid_floor · threshold`` (:meth:`Region.count_low`), which
        the next step's extension check reads."""
        self._low = self.regions.count_low(self.spde, self.params.trigger, True)

    def _extension_due(self) -> bool:
        """Whether an uncovered cell holds fewer than ``regrid_floor · threshold`` particles (counted
        at the end of the last step, or now where that step was a plain SPDE step or a state was loaded)."""
        if self._low is None:
            self._low = self.regions.count_low(self.spde, self.params.trigger, False)
        return self._low > 0

    def step(self, n: int) -> None:
        """Advance from step ``n`` to ``n + 1`` (see the class docstring)."""
        self._change = 0.0
        if self.regrid_interval and n > 0:
            t = _clock()
            if n % self.regrid_interval == 0:
                self.regrid(n)
            elif self.params.regrid_floor > 0 and self._extension_due():
                self.extend(n)
            self.timing["regrid"] += _clock() - t
        t0 = _clock()
        self._low = None  # q changes from here
        if self.n_cover == 0:  # no particle region: a plain SPDE step
            self.spde.step(n)
            self.timing["spde"] += _clock() - t0
            return
        if self.substeps > 1:
            self.sampler.q_old.copy_from(self.spde.q)
        self._fill_ghosts(n * self.substeps, 0.0, self._tilt_on(n))
        t1 = _clock()
        self.spde.advance(n)
        t2 = _clock()
        self._particle_steps(n)
        self.diagnose()
        t3 = _clock()
        self.timing["spde"] += t2 - t1
        self.timing["particles"] += (t1 - t0) + (t3 - t2)

    def _particle_steps(self, n: int) -> None:
        """Steps 3 and 4 after the SPDE's: S1, the k particle sub-steps of Δt/k (ghosts from q
        interpolated in time), the synchronisation with the last (:meth:`Coupling.cross`)."""
        c, k = self.coupling, self.substeps
        for s in range(k):
            if s > 0:
                self._fill_ghosts(n * k + s, s / k, 1)
            c.cross(self.pool, self.cur, n * k + s, int(s == 0), int(s == k - 1), self.n_ring, self.n_cover)
            self._compact()

    def _compact(self) -> None:
        """Keep the marked particles (in place, or in the other buffer: the pointer layout, which may
        need a larger pool)."""
        self.pool, self.cur = self.pool.compacted(self.cur)

    def _tilt_on(self, n: int) -> int:
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
        for k in REGRID_LOG:
            st[f"regrid_{k}"] = np.array([r[k] for r in self.regrids])
        return st

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        self.spde.load_state({k[5:]: v for k, v in st.items() if k.startswith("spde_")})
        self.regions.load_state(st)
        self._low = None
        self.pool = self.pool.restored(st["x"], st["pid"], st["n_real"], self.regions.grown(self.regions.mask()))
        self.cur = 0
        self.regrids = [{k: st[f"regrid_{k}"][i].item() for k in REGRID_LOG} for i in range(len(st["regrid_step"]))]

    def density(self) -> np.ndarray:
        return self.spde.density()

    def region(self) -> np.ndarray:
        """The particle region of every member, ``(ensemble, *cells)`` booleans."""
        return self.regions.mask()

    def diagnostics(self) -> dict[str, float]:
        d = self.spde.diagnostics()
        c = self.coupling
        if self.n_cover:  # otherwise the last step was a plain SPDE step
            d["boundary_inflow"] = d["boundary_inflow"] + c.wall_inflow[None] + c.p_inflow[None]
            d["clamped_steps"] = int(c.clamped[None])
        d["particles"] = pools.total(self.pool.kept)
        d["regrid_change"] = self._change
        return d
