"""The AMAR hybrid (paper §3): the SPDE everywhere, real Brownian particles in a particle region."""

import math
import time

import numpy as np
import taichi as ti

from . import pool, regrid
from .fv import SPDESolver
from .ghosts import Sampler
from .grid import DIRICHLET, across, cell_of, exclusive_scan
from .particles import Walker
from .region import Region
from .solver import RegionSolver

# one record per regrid; on_demand: members regridded off schedule (0: a scheduled regrid of all)
REGRID_LOG = ("step", "boxes", "covered_cells", "efficiency", "created", "removed", "on_demand")


def _clock() -> float:
    """Seconds, after the device has finished what was launched (kernels may run asynchronously)."""
    ti.sync()
    return time.perf_counter()


@ti.data_oriented
class Coupling:
    r"""The particle step and the synchronisation of eq. (12): what the region and the SPDE
    exchange in one step (steps 3 and 4 of :class:`HybridSolver`)."""

    def __init__(self, spde: SPDESolver, region: Region, sampler: Sampler, walker: Walker):
        self.spde, self.region, self.sampler, self.walker = spde, region, sampler, walker
        self.grid, self.dim, self.n, self.real, self.dt = spde.grid, spde.dim, spde.n, spde.real, spde.dt
        E, n = spde.ensemble, spde.n
        self.count = ti.field(ti.i32, shape=(E, *n))  # particles ending the walk in each covered cell
        self.dN = ti.field(ti.i32, shape=(E, *n))  # ΔN: net particles the region gave each uncovered cell
        self.row = ti.field(ti.i32, shape=(E, math.prod(n[:-1])))  # first target slot of each member's rows of cells (sort)
        self.entered = ti.field(ti.u64, shape=(E, *n))  # bit k: ghost k of this cell walked into the region
        self.cap = ti.field(ti.i32, shape=(E, *n))  # most ghosts of this cell that may enter this sub-step
        self.clamped = ti.field(ti.i64, shape=())  # axis steps clamped to ±Δx in the last walk
        self.p_inflow = ti.field(ti.i64, shape=())  # particles injected minus absorbed at Dirichlet sides
        self.wall_inflow = ti.field(ti.f64, shape=())  # SPDE boundary inflow of covered cells (cancelled)

    @ti.func
    def _face(self, J, a: ti.template(), side: ti.template()):
        """Index in the SPDE's ``flux`` of face ``side`` (0: lower, 1: upper) of cell ``J`` along ``a``."""
        F = J
        if ti.static(side == 1):
            F = self.spde.upper(J, a)
        return F

    @ti.func
    def _cell(self, e, x):
        """The member-first index of the cell holding position ``x`` of member ``e``."""
        D = ti.Vector.zero(ti.i32, self.dim + 1)
        D[0] = e
        for a in ti.static(range(self.dim)):
            D[a + 1] = cell_of(x[a], self.real(self.grid.dx[a]), self.n[a])
        return D

    @ti.kernel
    def walk(self, pool: ti.template(), cur: ti.i32, step: ti.i32, last: ti.i32):
        """Step 3 (one particle sub-step): walk, mark to keep what ends in the region, add to ΔN;
        on the ``last`` sub-step count the particles per covered cell. The ghosts of this
        sub-step were walked by the fill, which kept only those that entered the region
        (:meth:`Sampler.sample`): here they are only accounted for."""
        self.clamped[None] += self.sampler.clamped[None]  # the ghosts' clamped steps, all of them
        for u in range(pool.units(cur)):
            e, U, lo, hi = pool.unit(cur, u)
            for k in range(self.walker.rounds(lo, hi)):
                for I, ident, x, y, alive, clamped, own in ti.static(
                        self.walker.lanes_at(pool, cur, U, e, lo, hi, k, ti.u32(step))):
                    if own:  # a repeated last slot is accounted once
                        self._account(pool, I, e, ident, x, y, alive, clamped, step, last)

    @ti.func
    def _account(self, pool: ti.template(), I, e, ident, x, y, alive, clamped, step, last):
        """A walked slot of :meth:`walk`: store its step (a ghost of this sub-step was walked by the
        fill: it keeps ``x``), mark it to keep if it ends in the region, and count the crossing."""
        ghost = ident[1] == ti.u32(step + 1)
        if ghost:
            y, alive, clamped = x, True, 0
        if clamped:  # rare (p ≈ erfc(Δx/√(2Δt)) per axis): no atomic on the shared counter otherwise
            self.clamped[None] += clamped
        D = self._cell(e, y)
        keep = alive and self.region.covered[D] != 0
        pool.x[I] = y
        pool.mark(I, keep, D)
        if keep:
            counted = True
            if ghost:
                O = self.sampler.origin(ident[0])
                if self.region.inside(O):
                    k = self.sampler.index(ident[0])
                    if k < 64:  # settled by cap_entries
                        ti.atomic_or(self.entered[self.region.member(e, O)], ti.u64(1) << ti.cast(k, ti.u64))
                        counted = False
                    else:
                        self.dN[self.region.member(e, O)] -= 1
                else:
                    self.p_inflow[None] += 1
            if last and counted:
                self.count[D] += 1
        elif not ghost:
            if alive:
                self.dN[D] += 1
            else:
                self.p_inflow[None] -= 1

    @ti.func
    def _row(self, R):
        """The index in :attr:`row` of row ``R`` (member, then the cell index without its last axis)."""
        r = 0
        for a in ti.static(range(1, self.dim)):
            r = r * self.n[a - 1] + R[a]
        return ti.Vector([R[0], r])

    @ti.kernel
    def sort(self, pool: ti.template(), b: ti.i32):
        """Compact buffer ``b`` of a flat pool (:class:`pool.ParticlePool`) into the other like
        its ``compact`` (the marked slots), but in cell order (a counting sort: counts per cell in ``count``, a
        scan over rows of cells, a scatter). A particle's random numbers are keyed on its identity,
        so the order changes no result; it keeps the walk's cell lookups and ``count`` updates
        local, where the order left by many steps of compaction and appended ghosts scatters them
        over the grid (measured in sphere3d at step 200: the walk 296–365 → 177–208 ms a step).
        A pointer pool keeps its particles by block of cells and needs no sort."""
        E, L, rows = ti.static(self.spde.ensemble, self.n[-1], math.prod(self.n[:-1]))
        for u in range(pool.units(b)):
            e, U, lo, hi = pool.unit(b, u)
            for p in range(lo, hi):
                I = pool.index(b, U, p)
                if pool.marked(I):
                    self.count[self._cell(e, pool.x[I])] += 1
        # rows of cells along the last axis, member first. (Taichi 1.7.4: reaching a row's cells
        # through Region.unflatten of a flat row index here failed to compile, "Assertion failure:
        # load_src->is<MatrixPtrStmt>() ..." in store_to_load_forwarding; a grouped ndrange works.)
        for R in ti.grouped(ti.ndrange(E, *self.n[:-1])):  # particles per row
            c = 0
            for j in range(L):
                c += self.count[ti.Vector([R[a] for a in ti.static(range(self.dim))] + [j])]
            self.row[self._row(R)] = c
        ti.loop_config(serialize=True)  # the scan over each member's rows (grid.exclusive_scan: a serial task)
        for e in range(E):
            total = exclusive_scan(self.row, e, rows)
            pool.n[1 - b, e] = total
            pool.kept[e] = total
        for R in ti.grouped(ti.ndrange(E, *self.n[:-1])):  # count becomes each cell's next target slot
            total = self.row[self._row(R)]
            for j in range(L):
                J = ti.Vector([R[a] for a in ti.static(range(self.dim))] + [j])
                c = self.count[J]
                self.count[J] = total
                total += c
        for u in range(pool.units(b)):
            e, U, lo, hi = pool.unit(b, u)
            for p in range(lo, hi):
                I = pool.index(b, U, p)
                if pool.marked(I):
                    K = pool.index(1 - b, U, ti.atomic_add(self.count[self._cell(e, pool.x[I])], 1))
                    pool.x[K] = pool.x[I]
                    pool.pid[K] = pool.pid[I]
        for J in ti.grouped(self.count):
            self.count[J] = 0

    @ti.kernel
    def cap_entries(self, pool: ti.template(), cur: ti.i32, step: ti.i32, last: ti.i32, n_ring: ti.i32):
        """Let at most ``⌊q_I V_c + ΔN_I⌋`` of the ghosts of cell ``I`` enter the region in this
        sub-step: the content the SPDE left in it (after S1) plus what the region gave it so far.
        Without this cap a ghost cell holding ``ℓ + α`` particles, ``ℓ + 1`` ghosts of which all
        walk in while its SPDE fluxes also carry content away, goes negative (measured: 6
        cell-steps in the default ellipse2d run, in cells holding 5–8 particles). The ghosts
        that enter are those of lowest index among the ones that walked in, so the result does
        not depend on thread order; cells with more than 64 ghosts are not capped (64 ghosts all
        walking in does not happen). Only the slots appended since the last compaction can hold
        this sub-step's ghosts, so only those are read (ellipse2d: that loop 0.19 → 0.09 ms a step)."""
        vol = ti.static(self.grid.cell_volume)
        for i in range(n_ring):
            J, inside = self.region.ring_cell(i)
            if inside:
                room = ti.floor(ti.cast(self.spde.q[J], ti.f64) * vol + ti.cast(self.dN[J], ti.f64))
                cap = ti.cast(ti.max(room, 0.0), ti.i32)
                self.cap[J] = cap
                self.dN[J] -= ti.min(ti.cast(ti.math.popcnt(self.entered[J]), ti.i32), cap)
        for u in range(pool.units(cur)):
            e, U, lo, hi = pool.unit(cur, u)
            for p in range(ti.max(lo, pool.first_new(U)), hi):
                I = pool.index(cur, U, p)
                ident = pool.pid[I]
                if pool.marked(I) and ident[1] == ti.u32(step + 1):
                    O = self.sampler.origin(ident[0])
                    k = self.sampler.index(ident[0])
                    if self.region.inside(O) and k < 64:
                        J = self.region.member(e, O)
                        below = self.entered[J] & ((ti.u64(1) << ti.cast(k, ti.u64)) - ti.u64(1))
                        if ti.cast(ti.math.popcnt(below), ti.i32) < self.cap[J]:
                            if last:
                                self.count[self._cell(e, pool.x[I])] += 1
                        else:
                            pool.unmark(I)
        for i in range(n_ring):
            J, inside = self.region.ring_cell(i)
            if inside:
                self.entered[J] = ti.u64(0)

    @ti.kernel
    def s1(self, n_ring: ti.i32):
        r"""S1 of eq. (12), before the walk: each ghost cell ``I`` drops the terms ∓ Δt F / Δx_a that
        eq. (9) applied across its faces with covered cells, ``q_I ← q_I^{n+1,*} − Σ_{S1} F^{i→I}/V_c``,
        so that ``q_I`` holds what the SPDE leaves in it; S2 (``ΔN_I / V_c``) is added by :meth:`sync`."""
        for i in range(n_ring):
            J, inside = self.region.ring_cell(i)
            if inside:
                corr = self.real(0.0)
                for a in ti.static(range(self.dim)):
                    k = self.real(self.dt / self.grid.dx[a])
                    # F is positive down the axis: F = ½ Δq/Δx + noise
                    for side in ti.static(range(2)):
                        K, has = across(self.grid, J, a, side)
                        if has and self.region.covered[K]:
                            if ti.static(side == 0):
                                corr += k * self.spde.flux[self._face(J, a, side)][a]
                            else:
                                corr -= k * self.spde.flux[self._face(J, a, side)][a]
                self.spde.q[J] += corr

    @ti.kernel
    def sync(self, n_cover: ti.i32, n_ring: ti.i32):
        """Step 4: covered cells take their counts; ring cells add S2, ΔN / V_c (eq. 12)."""
        vol = ti.static(self.grid.cell_volume)
        self.wall_inflow[None] = 0.0
        for i in range(n_cover + n_ring):  # one parallel loop: covered cells, then ring cells
            if i < n_cover:
                self._take_count(self.region.covered_cell(i))
            else:
                J, inside = self.region.ring_cell(i - n_cover)
                if inside:
                    self.spde.q[J] += self.real(ti.cast(self.dN[J], ti.f64) / vol)
                    self.dN[J] = 0

    @ti.func
    def _take_count(self, J):
        """Synchronise covered cell ``J``: q = N / V_c; the SPDE's flux through a Dirichlet side of
        it did not happen and is recorded in ``wall_inflow``."""
        vol = ti.static(self.grid.cell_volume)
        self.spde.q[J] = self.real(ti.cast(self.count[J], ti.f64) / vol)
        self.count[J] = 0
        for a in ti.static(range(self.dim)):
            area = ti.static(self.grid.face_area[a] * self.dt)
            for side in ti.static(range(2)):
                if ti.static(self.grid.boundary[a][side] == DIRICHLET):
                    _, inside = across(self.grid, J, a, side)
                    if not inside:
                        F = ti.cast(self.spde.flux[self._face(J, a, side)][a], ti.f64) * area
                        if ti.static(side == 0):
                            self.wall_inflow[None] += F
                        else:
                            self.wall_inflow[None] -= F


class HybridSolver(RegionSolver):
    r"""SPDE on the whole grid coupled to particles in a region (paper §3.1–3.2).

    One step ``n → n+1``:

    1. the ghost ring (cells outside the region within Chebyshev distance 1 of it, and Dirichlet
       reservoir cells beyond covered boundary cells) gets ``ℓ`` particles plus one with
       probability ``α``, where ``ℓ + α = max(q_I^n, 0) V_c`` (paper §3), placed with the linear
       profile of :meth:`Sampler.tilt` (the slope of the deterministic q̄, by default);
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
    0 keeps the first region): tag,
    buffer and Berger–Rigoutsos per member; particles in cells that stay covered are kept, cells
    that leave the region keep their count as density, newly covered cells are sampled from the
    SPDE (the only step that changes the total; logged in ``regrids``). At the start the state is
    the piecewise-constant initial condition, so those particles lie uniformly in their cells.
    """

    def __init__(self, spde: SPDESolver, params: regrid.RegridParams, regrid_interval: int,
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
        self.pool = pool.make(pool_layout, grid, self.ensemble, self.real)  # flat or pointer (pool.LAYOUTS)
        self.cur = 0  # the pool buffer holding the particles between steps
        self.regrids: list[dict] = []  # one record per regrid
        self._change = 0.0  # created − removed at this step's regrid
        self._removed = 0.0  # SPDE content Σ q V_c of the cells the last regrid covered anew
        self.timing = {"spde": 0.0, "particles": 0.0, "regrid": 0.0}  # seconds spent in each part

    @property
    def boxes(self) -> list[list[regrid.Box]]:
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
        self.spde.diagnose()

    def step(self, n: int) -> None:
        """Advance from step ``n`` to ``n + 1`` (see the class docstring)."""
        self._change = 0.0
        if self.regrid_interval and n > 0:
            t = _clock()
            if n % self.regrid_interval == 0:
                self.regrid(n)
            elif self.params.floor > 0:
                p = self.params
                if self.regions.mark_low(self.spde.q, p.floor * p.threshold, p.threshold):
                    self.extend(n)
            self.timing["regrid"] += _clock() - t
        t0 = _clock()
        if self.n_cover == 0:  # no particle region: a plain SPDE step
            self.spde.step(n)
            self.timing["spde"] += _clock() - t0
            return
        if self.substeps > 1:
            self.sampler.q_old.copy_from(self.spde.q)
        self._fill_ghosts(n * self.substeps, 0.0, self._tilt_on(n))
        t1 = _clock()
        self.spde.fluxes(n)
        self.spde.update()
        t2 = _clock()
        self._particle_steps(n)
        self.spde.diagnose()
        t3 = _clock()
        self.timing["spde"] += t2 - t1
        self.timing["particles"] += (t1 - t0) + (t3 - t2)

    def _particle_steps(self, n: int) -> None:
        """Steps 3 and 4 after the SPDE's: S1, the k particle sub-steps of Δt/k (ghosts from q
        interpolated in time), then the synchronisation."""
        c, k = self.coupling, self.substeps
        c.s1(self.n_ring)
        c.clamped[None] = 0
        c.p_inflow[None] = 0
        for s in range(k):
            if s > 0:
                self._fill_ghosts(n * k + s, s / k, 1)
            c.walk(self.pool, self.cur, n * k + s, int(s == k - 1))
            c.cap_entries(self.pool, self.cur, n * k + s, int(s == k - 1), self.n_ring)
            self._compact()
        c.sync(self.n_cover, self.n_ring)

    def _compact(self) -> None:
        """Keep the marked particles, in the other buffer (the pointer layout may need a larger pool)."""
        self.pool = self.pool.compacted(self.cur)
        self.cur = 1 - self.cur

    def _tilt_on(self, n: int) -> int:
        """Whether particles sampled at step ``n`` are tilted: not at the start with ``mean``, where
        q̄ is the piecewise-constant initial condition (particles lie uniformly in each cell)."""
        return int(self.profile != "mean" or n > 0)

    def _fill_ghosts(self, sub: int, w: float, tilt_on: int) -> None:
        """Ghosts for particle sub-step ``sub`` from ``(1 − w) q^n + w q^{n+1,*}`` (for s > 0 after S1,
        :meth:`Coupling.s1`: what the SPDE left in the ghost cell); the fill is a pure
        function of its inputs, so a pool that is too small is grown and the fill redone."""
        while True:
            self.sampler.fill(self.pool, self.cur, sub, self.n_ring, w, tilt_on, 1)
            need = self.sampler.check_need()
            if need <= self.pool.capacity:
                return
            self.pool = self.pool.grown(2 * need)
            self.pool.truncate(self.cur)

    def regrid(self, n: int) -> None:
        """New region from the SPDE density at step ``n`` (tag, buffer, Berger–Rigoutsos)."""
        ppc = self._content()
        masks, tagged = self.regions.plan(ppc)
        self._set_region(masks, n, ppc, sort=True)
        self._log(n, tagged, 0)

    def extend(self, n: int) -> None:
        """Cover, before step ``n``, the cells :meth:`Region.mark_low` marked (grown by the buffer,
        clustered by Berger–Rigoutsos) and keep the rest of the region: the on-demand regrid.

        Tagging promises that no uncovered cell holds fewer than ``threshold`` particles; between
        scheduled regrids that promise breaks, and FV then goes negative (one 2D step at C = 1/16
        moves about √N/2 particles). An extension is due when an uncovered cell holds fewer than
        ``regrid_floor · threshold``; it then covers every uncovered cell below ``threshold``, so
        the next one waits until a cell falls from above ``threshold`` to below the floor
        (hysteresis; with ``regrid_floor = 1`` the two sets are the same and an extension comes on
        most steps of ellipse2d). Together with the ghost-entry cap of :meth:`Coupling.cap_entries`
        this cut the negative cell-steps of ellipse2d at threshold 5 from 47 to 1 (an FV step of
        4.7 σ from 5.6 particles); the cap alone to 8.
        """
        ppc = self._content()
        masks, members = self.regions.plan_extension()
        self._set_region(masks, n, ppc)
        self._log(n, int(regrid.tag(ppc, self.params.threshold).sum()), members)

    def _content(self) -> np.ndarray:
        """The SPDE content of every cell, ``q V_c`` (particles per cell, float64), scaled in place:
        :meth:`SPDESolver.density` returns a fresh array, so a regrid makes one grid-sized array
        here, not two (17 MB each at 128³, at each of sphere3d's 579 regrids)."""
        ppc = self.spde.density()
        ppc *= self.grid.cell_volume
        return ppc

    def _log(self, n: int, tagged: int, on_demand: int) -> None:
        covered = self.n_cover
        self.regrids.append({"step": n, "boxes": sum(len(b) for b in self.boxes), "covered_cells": covered,
                             "efficiency": tagged / covered if covered else 1.0,
                             "created": int(self.sampler.created[None]), "removed": self._removed,
                             "on_demand": on_demand})

    def set_region(self, masks: np.ndarray, n: int) -> None:
        """Make ``masks`` (``(ensemble, *cells)`` booleans) the particle region at step ``n``, its
        diagnostics up to date (a region set from outside, between steps)."""
        self._set_region(masks, n, self._content())
        self.spde.diagnose()

    def _set_region(self, masks: np.ndarray, n: int, ppc: np.ndarray, sort: bool = False) -> None:
        """:meth:`set_region` inside a step (regrid, extension), where the step's own
        synchronisation brings the diagnostics up to date: no full-grid pass here. With ``sort``
        (the scheduled regrids) the kept particles are put in cell order (:meth:`Coupling.sort`).
        Between steps every particle lies in a covered cell, so a region that only grows keeps
        them all where they are (:meth:`pool.ParticlePool.settle`; the compaction it replaces
        copied 5 M particles, 17 ms, at each of sphere3d's 513 extensions)."""
        masks = np.broadcast_to(masks, (self.ensemble, *self.n))
        old = self.regions.mask()
        grown = self.regions.grown(masks)
        near = grown | old  # where particles can be while the region moves: old, new, ring
        self.pool = self.pool.fitted(self._estimate(masks, near, ppc), near)
        sort = sort and not self.pool.cell_ordered
        cells, n_new, n_gone = self.regions.stage(masks)
        # the SPDE content the newly covered cells held, summed here: the same bits on any thread count
        self._removed = float(ppc.reshape(-1)[cells[:n_new]].sum())
        self.sampler.cover(self.pool, self.cur, n * self.substeps, self._tilt_on(n), self.coupling.count,
                           cells, n_new, n_gone, int(sort or n_gone > 0))
        if sort:
            self.coupling.sort(self.pool, self.cur)
            self.cur = 1 - self.cur
        elif n_gone:
            self._compact()
        else:  # the region only grew (every extension): no particle leaves, a compaction would copy them all
            self.pool.settle(self.cur)
        self.pool.retain(grown)  # the new region and its ring
        self.regions.lists(grown)
        if self.sampler.check_need() > self.pool.capacity:  # the estimate bounds it; kept as a guard
            raise RuntimeError("particle pool estimate too small at a regrid")
        self._change += self.sampler.created[None] - self._removed

    def _estimate(self, masks: np.ndarray, near: np.ndarray, ppc: np.ndarray) -> np.ndarray:
        """Slots each cell can ask for around a regrid (``(ensemble, *cells)``; the pool adds the
        headroom of :func:`pool.capacity`): the region and its ghost ring full, and a covered
        cell's reservoir ghosts."""
        need = np.maximum(ppc, 0)  # in place from here: one grid-sized array per regrid, not three
        need *= near
        np.ceil(need, out=need)
        if self.grid.has_dirichlet:
            need += self.grid.reservoir_ppc_max * 3 ** (self.dim - 1) * masks
        return need

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
        d["particles"] = pool.total(self.pool.kept)
        d["regrid_change"] = self._change
        return d
