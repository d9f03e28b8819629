"""The particle step of the AMAR hybrid and its synchronisation with the SPDE (paper §3.2, eq. 12):
the walk with crossing counts, the ghost-entry cap, the cell-order sort, S1/S2 refluxing."""

import math
import time

import taichi as ti

from ..core.grid import DIRICHLET, across, cell_of, exclusive_scan, light, spread
from ..methods.fv import SPDESolver
from ..methods.particles import Walker
from .ghosts import Sampler
from .region import Region


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
    def cross(self, pool: ti.template(), cur: ti.i32, step: ti.i32, first: ti.i32, last: ti.i32, n_ring: ti.i32,
              n_cover: ti.i32, trigger: ti.f64):
        """One particle sub-step in one launch (parallel loops run in order): the walk (:meth:`_walk`),
        the entry cap (:meth:`_cap`, with S1 on the ``first`` sub-step), the synchronisation
        (:meth:`_sync`, on the ``last``), the compaction of a pool that compacts in place
        (:meth:`ParticlePool.compact_here`; another compacts after the launch), the SPDE's diagnostics
        with the uncovered cells below ``trigger`` (:meth:`Region.count_low_here`)."""
        if first:
            self.clamped[None], self.p_inflow[None] = 0, 0
        self._walk(pool, cur, step, last)
        self._cap(pool, cur, step, first, last, n_ring)
        if last:
            self.wall_inflow[None] = 0.0
        self._sync(n_cover * last, n_ring, last)
        if ti.static(pool.in_place):
            pool.compact_here(cur)
        self.region.count_low_here(self.spde, trigger, True)

    @ti.func
    def _walk(self, pool: ti.template(), cur, step, last):
        """Step 3 (one particle sub-step): walk, mark to keep what ends in the region, add to ΔN; on the
        ``last`` sub-step count the particles per covered cell. The slots appended since the last
        compaction hold this sub-step's entrants, placed by the fill (:meth:`Sampler.sample`): only accounted for."""
        self.clamped[None] += self.sampler.clamped[None]  # the clamped steps of the ghosts that entered
        units = pool.units(cur)
        for u, s in ti.ndrange(units, spread(units)):  # a few hundred units would run on one thread
            if s != 0:
                continue
            e, U, lo, mid, hi = pool.split_unit(cur, u)
            for k in range(self.walker.rounds(lo, mid)):
                for I, ident, x, y, alive, clamped, own in ti.static(
                        self.walker.lanes_at(pool, cur, U, e, lo, mid, k, ti.u32(step))):
                    if own:  # a repeated last slot is accounted once
                        self._account(pool, I, e, ident, y, alive, clamped, False, last)
            for p in range(mid, hi):
                I = pool.index(cur, U, p)
                ident = pool.pid[I]
                self._account(pool, I, e, ident, pool.x[I], True, 0, True, last)

    @ti.func
    def _account(self, pool: ti.template(), I, e, ident, y, alive, clamped, ghost: ti.template(), last):
        """A slot of :meth:`walk` at ``y`` after its step (a ``ghost`` of this sub-step was walked by
        the fill): store it, mark it to keep if it ends in the region, count the crossing."""
        if clamped:  # rare (p ≈ erfc(Δx/√(2Δt)) per axis): no atomic on the shared counter otherwise
            self.clamped[None] += clamped
        D = self._cell(e, y)
        keep = alive and self.region.covered[D] != 0
        if ti.static(not ghost):
            pool.x[I] = y
        pool.mark(I, keep, D)
        if keep:
            counted = True
            if ti.static(ghost):
                O = self.sampler.origin(ident[0])
                if self.region.inside(O):
                    k = self.sampler.index(ident[0])
                    if k < 64:  # settled by _cap
                        ti.atomic_or(self.entered[self.region.member(e, O)], ti.u64(1) << ti.cast(k, ti.u64))
                        counted = False
                    else:
                        self.dN[self.region.member(e, O)] -= 1
                else:
                    self.p_inflow[None] += 1
            if last and counted:
                self.count[D] += 1
        elif ti.static(not ghost):
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
        """Compact buffer ``b`` of a flat pool (:class:`pools.ParticlePool`) into the other, in cell
        order (a counting sort: counts per cell in ``count``, a scan over rows, a scatter). The order
        changes no result (a particle's numbers are keyed on its identity) but keeps the walk's
        lookups local (measured faster). A pointer pool keeps its particles by block: no sort."""
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

    @ti.func
    def _cap(self, pool: ti.template(), cur, step, first, last, n_ring):
        """Let at most ``⌊q_I V_c + ΔN_I⌋`` of the ghosts of cell ``I`` enter the region in this
        sub-step: the content the SPDE left in it (after S1) plus what the region gave it so far
        (else a ghost cell of ``ℓ + α`` particles whose ``ℓ + 1`` ghosts all walk in while its SPDE
        fluxes carry content away goes negative: it did in ellipse2d). Those of lowest index enter,
        whatever the thread order; a cell of over 64 ghosts is not capped (never all walk in). Only
        the new slots are read. On the ``first`` sub-step a ring cell takes S1 (:meth:`_s1`) first."""
        vol = ti.static(self.grid.cell_volume)
        ti.loop_config(serialize=ti.static(light(self.dim)))
        for i in range(n_ring):
            J, inside = self.region.ring_cell(i)
            if inside:
                if first:
                    self._s1(J)
                room = ti.floor(ti.cast(self.spde.q[J], ti.f64) * vol + ti.cast(self.dN[J], ti.f64))
                cap = ti.cast(ti.max(room, 0.0), ti.i32)
                self.cap[J] = cap
                self.dN[J] -= ti.min(ti.cast(ti.math.popcnt(self.entered[J]), ti.i32), cap)
        units = pool.new_units(cur)  # (a serial loop: a loop_config before it would be its, not the next's)
        ti.loop_config(serialize=ti.static(light(self.dim)))
        for u in range(units):
            e, U, lo, hi = pool.new_unit(cur, u)
            for p in range(lo, hi):
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

    @ti.func
    def _s1(self, J):
        r"""S1 of eq. (12) for ghost cell ``J``, before the entry cap (:meth:`_cap`): it drops the terms
        ∓ Δt F / Δx_a of eq. (9) across its faces with covered cells, ``q_I ← q_I^{n+1,*} − Σ_{S1} F^{i→I}/V_c``,
        so that ``q_I`` holds what the SPDE leaves in it; S2 (``ΔN_I / V_c``) is added by :meth:`_sync`."""
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
        self.spde.q[J] = self.spde.q[J] + corr  # a plain store: each ring cell once (`+=` on a field is an atomic)

    @ti.func
    def _sync(self, n_cover, n_ring, last):
        """Step 4 (``last``; ``n_cover`` is 0 on the other sub-steps): covered cells take their counts;
        ring cells add S2, ΔN / V_c (eq. 12). Every sub-step: a ring cell's ``entered`` is cleared."""
        vol = ti.static(self.grid.cell_volume)
        ti.loop_config(serialize=ti.static(light(self.dim)))
        for i in range(n_cover + n_ring):  # one loop: covered cells, then ring cells
            if i < n_cover:
                self._take_count(self.region.covered_cell(i))
            else:
                J, inside = self.region.ring_cell(i - n_cover)
                if inside:
                    self.entered[J] = ti.u64(0)
                    if last:
                        self.spde.q[J] = self.spde.q[J] + self.real(ti.cast(self.dN[J], ti.f64) / vol)  # plain store, as in _s1
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


