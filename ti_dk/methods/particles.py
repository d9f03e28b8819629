"""Independent Brownian particles: sampling from a density, the clamped walk, and binning."""
import math

import numpy as np
import taichi as ti

from .. import pools
from ..core import rng
from ..core.expr import taichi_value
from ..core.grid import DIRICHLET, NEUMANN, PERIODIC, Grid, cell_of
from .solver import Solver

TABLE_REFINE = {1: 16, 2: 4, 3: 1}  # lattice points per cell and axis of a callable potential's gradient table


@ti.data_oriented
class Walker:
    r"""The stateless particle numerics shared by the particle and hybrid solvers (ti.funcs only).

    A step of particle ``(id0, birth)`` of member ``e`` at step ``n`` is

    .. math:: x_a \leftarrow x_a + \operatorname{clamp}(-\tfrac12 ∂_aU(x)\, Δt + \sqrt{Δt}\, Z_a, -Δx_a, Δx_a),

    with ``Z`` keyed on (seed, member, step, id0, birth): the same whichever thread or slot holds it.
    One Philox-4x32-10 counter serves the ``G = 4 // dim`` particles ``id0 = G·k … G·k + G − 1``
    (4 in 1D, 2 in 2D, 1 in 3D): particle ``id0`` takes words ``(id0 mod G)·dim + a``, so a loop
    that holds consecutive identities together (:meth:`ParticleSolver._walk`) makes one call
    for ``G`` particles, and a particle walked alone (:meth:`move`) draws the same numbers. With
    ``alone`` (a loop whose particles each make their own call: the hybrid's) an iteration moves
    :func:`rng.lanes` particles, their calls side by side.

    The drift of an external potential U (``grid.potential``; Euler–Maruyama, ∇U at the position
    before the step, the whole axis step clamped so a particle still moves at most one cell) is
    compiled in only with one: a formula's gradient is differentiated symbolically
    (:func:`~ti_dk.core.expr.derivative`) and compiled to arithmetic; a callable's is read from
    a table of central differences of U on a lattice :data:`TABLE_REFINE` times finer than the
    grid (nearest lattice point), one cell beyond each side for the reservoirs.
    """

    def __init__(self, grid: Grid, dt: float, real, key: tuple[int, int], member0: int = 0, alone: bool = False):
        self.grid, self.dt, self.real = grid, dt, real
        self.member0 = member0  # global index of member 0 (random numbers are keyed on the global index)
        self.dim = grid.dim
        self.group = max(1, 4 // self.dim)  # consecutive identities sharing one Philox counter
        # counter groups (or, ``alone``, particles each with its own Philox call) a walk loop iteration moves
        self.lanes = rng.lanes(self.dim, alone=alone)
        self.key = key  # the Philox key of the run (rng.seed_key of its seed)
        rng.prepare()
        self.drifting = grid.potential is not None  # the drift −½∇U Δt is compiled in
        self.grads = None  # formulas of ∂_aU
        self.formula = self.drifting and grid.potential.tree is not None  # else a callable: a table
        if self.formula:
            self.grads = grid.potential.gradient_trees()
        elif self.drifting:
            self._tabulate(grid.potential)

    def _tabulate(self, potential) -> None:
        """A callable potential's gradient on the lattice of :meth:`drift` (points ``(k + ½) h/r − h``)."""
        r = self.refine = TABLE_REFINE[self.dim]
        pts = [(np.arange((n + 2) * r) + 0.5) * (h / r) - h for n, h in zip(self.grid.cells, self.grid.dx)]
        u = potential(*np.meshgrid(*pts, indexing="ij", sparse=True))
        g = np.stack([np.gradient(u, h / r, axis=a) for a, h in enumerate(self.grid.dx)], axis=-1)
        self.table = ti.Vector.field(self.dim, self.real, shape=u.shape)  # ∂_aU on the lattice [1/length]
        self.table.from_numpy(g.astype(np.float32 if self.real == ti.f32 else np.float64))

    @ti.func
    def drift(self, x):
        """The drift displacement −½ ∇U(x) Δt of one step from position ``x``."""
        g = ti.Vector.zero(self.real, self.dim)
        if ti.static(self.formula):
            coords = [x[a] for a in ti.static(range(self.dim))]
            for a in ti.static(range(self.dim)):
                g[a] = taichi_value(self.grads[a], coords, self.real)
        else:
            K = ti.Vector.zero(ti.i32, self.dim)
            for a in ti.static(range(self.dim)):
                h = ti.static(self.grid.dx[a] / self.refine)
                K[a] = cell_of(x[a] + self.real(self.grid.dx[a]), self.real(h), self.table.shape[a])
            g = self.table[K]
        return self.real(-0.5 * self.dt) * g

    @ti.func
    def bits(self, e, id0, birth, step):
        """The Philox words of the counter group holding particle ``(id0, birth)`` of member ``e``."""
        return rng.philox4x32(ti.math.uvec4(id0 // ti.u32(self.group), step, self.member(e),
                                            ti.u32(rng.WALK) | (birth << rng.PURPOSE_BITS)),
                              ti.math.uvec2(self.key[0], self.key[1]))

    @ti.func
    def own(self, bits, id0):
        """The Philox words of the group with particle ``id0``'s own ``dim`` words first."""
        words = ti.math.uvec4(bits[0], bits[1], bits[2], bits[3])
        if ti.static(self.group > 1):
            g = ti.cast(id0 % ti.u32(self.group), ti.i32) * self.dim
            for k in ti.static(range(1, self.group)):
                if g == k * self.dim:
                    for a in ti.static(range(self.dim)):
                        words[a] = bits[k * self.dim + a]
        return words

    @ti.func
    def move(self, x, e, id0, birth, step):
        """One clamped Brownian step of the particle (id0, birth) of member ``e``; applies the walls.

        Returns the new position, whether it is still in the domain, and the number of clamped axes.
        """
        return self.step_with(x, self.own(self.bits(e, id0, birth, step), id0), 0)

    @ti.func
    def rounds(self, lo, hi):
        """Iterations of a walk over the slots ``[lo, hi)`` that moves :attr:`lanes` slots at a time
        (:meth:`lanes_at`)."""
        return (hi - lo + self.lanes - 1) // self.lanes

    @ti.func
    def lanes_at(self, pool: ti.template(), b, U, e, lo, hi, k, step):
        """Iteration ``k`` of :meth:`rounds` over the slots ``[lo, hi)`` of unit ``U`` in buffer ``b`` of
        ``pool`` (member ``e``): its :attr:`lanes` slots ``lo + L·k + l``, their Philox calls made
        first (:func:`rng.lanes`), each moved by :meth:`move`. Past ``hi`` a lane repeats the last slot.

        Returns a list with one tuple per lane, ``(I, ident, x, y, alive, clamped, own)``: the
        slot's index in ``pool``, identity and position, :meth:`move`'s result, and whether the
        lane is the slot's own (store and count only then; the repeats of the last slot are not).
        """
        L = ti.static(self.lanes)
        Is = [pool.index(b, U, ti.min(lo + L * k + l, hi - 1)) for l in ti.static(range(L))]
        idents = [pool.pid[Is[l]] for l in ti.static(range(L))]
        bits = [self.bits(e, idents[l][0], idents[l][1], step) for l in ti.static(range(L))]
        xs = [pool.x[Is[l]] for l in ti.static(range(L))]
        moved = [self.step_with(xs[l], self.own(bits[l], idents[l][0]), 0) for l in ti.static(range(L))]
        return [(Is[l], idents[l], xs[l], moved[l][0], moved[l][1], moved[l][2], lo + L * k + l < hi)
                for l in ti.static(range(L))]

    @ti.func
    def step_with(self, x, bits, g: ti.template()):
        """The step of :meth:`move` from the words ``bits[g·dim + a]`` (``g`` a compile-time slot)."""
        y = x
        alive = True
        clamped = 0
        drift = ti.Vector.zero(self.real, self.dim)
        if ti.static(self.drifting):
            drift = self.drift(x)
        for a in ti.static(range(self.dim)):
            ya, ok, c, _raw = self.axis_step(x[a], a, bits[g * self.dim + a], drift[a])
            y[a] = ya
            alive = alive and ok
            clamped += c
        return y, alive, clamped

    @ti.func
    def axis_step(self, xa, a: ti.template(), word, drift):
        """Axis ``a`` of :meth:`step_with`: coordinate ``xa`` moved by ``√Δt Z + drift`` (``Z`` from
        ``word``) clamped to ±Δx_a, then the axis's walls. Returns the new coordinate, whether it is
        still in the domain, 1 if the step was clamped (else 0), and ``xa + step`` before the walls."""
        h = ti.static(self.grid.dx[a])
        L = ti.static(self.grid.lengths[a])
        lo, hi = ti.static(self.grid.boundary[a])
        alive = True
        clamped = 0
        d = self.real(self.dt**0.5) * rng.normal(word, self.real)
        if ti.static(self.drifting):
            d += drift
        if ti.abs(d) > h:
            d = ti.math.clamp(d, -self.real(h), self.real(h))
            clamped = 1
        raw = xa + d
        ya = raw
        if ti.static(lo == PERIODIC):
            if ya < 0:
                ya += self.real(L)
            elif ya >= self.real(L):
                ya -= self.real(L)
        else:
            if ya < 0:
                if ti.static(lo == NEUMANN):
                    ya = -ya
                else:
                    alive = False
            elif ya > self.real(L):
                if ti.static(hi == NEUMANN):
                    ya = self.real(2 * L) - ya
                else:
                    alive = False
        return ya, alive, clamped, raw

    @ti.func
    def member(self, e):
        """The counter word of local member ``e``: its global index (:func:`rng.member_word`)."""
        return rng.member_word(self.key, self.member0, e)

    @ti.func
    def in_cell(self, C, bits, tilt):
        r"""A position in cell ``C`` (integer vector, may lie in a ghost layer).

        Along each axis the offset ``u ∈ (0, 1)`` has density ``1 + b (u − ½)`` with
        ``b = tilt[a] ∈ [−2, 2]`` (0: uniform, as in paper §3), drawn by inverting its CDF
        ``u + b (u² − u)/2 = r`` in the cancellation-free form ``u = 2r / (c + √(c² + 2br))``,
        ``c = 1 − b/2``. (With a potential the hybrid lays its particles along e^{−U} instead:
        :meth:`ti_dk.hybrid.incell.InCell.place`.)
        """
        y = ti.Vector.zero(self.real, self.dim)
        for a in ti.static(range(self.dim)):
            y[a] = (self.real(C[a]) + self.in_cell_axis(bits[a], tilt[a])) * self.real(self.grid.dx[a])
        return y

    @ti.func
    def in_cell_axis(self, word, tilt):
        """One axis of :meth:`in_cell`: the offset ``u ∈ (0, 1)`` from ``word`` with density
        ``1 + tilt (u − ½)``."""
        r = rng.uniform(word, self.real)
        b = self.real(tilt)
        c = self.real(1.0) - self.real(0.5) * b
        u = self.real(2.0) * r / (c + ti.sqrt(ti.max(c * c + self.real(2.0) * b * r, self.real(0.0))))
        return ti.min(u, self.real(1.0 - 2.0**-24))  # stay inside the cell whatever the rounding

    @ti.func
    def how_many(self, lam, bits_word):
        """ℓ particles plus one more with probability α, for a mean of λ = ℓ + α (paper §3)."""
        ell = ti.floor(lam)
        extra = 0
        if rng.uniform(bits_word, ti.f64) < lam - ell:
            extra = 1
        return ti.cast(ell, ti.i32) + extra


@ti.data_oriented
class Placement:
    """The initial placements of :class:`ParticleSolver` (kernels on its pool, walker and key):
    per cell, uniform in the domain, or a fixed total drawn by cell."""

    @ti.kernel
    def _sample(self, ppc: ti.template()):
        key = ti.math.uvec2(self.key[0], self.key[1])
        self.overflow[None] = 0
        for e in range(self.ensemble):
            k = 0
            for C in ti.grouped(ti.ndrange(*self.n)):  # serial within a member: slots in cell order
                lin = ti.u32(0)
                for a in ti.static(range(self.dim)):
                    lin = lin * ti.u32(self.n[a]) + ti.u32(C[a])
                bits = rng.philox4x32(ti.math.uvec4(lin, 0, self.walker.member(e), ti.u32(rng.SAMPLE_COUNT)), key)
                m = self.walker.how_many(ppc[C], bits[0])
                for _ in range(m):
                    if k < self.capacity:
                        r = rng.philox4x32(ti.math.uvec4(ti.u32(k), 0, self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
                        self.pool.x[0, e, k] = self.walker.in_cell(C, r, ti.Vector.zero(self.real, self.dim))
                    k += 1
            if k > self.capacity:
                self.overflow[None] = 1
            self.pool.n[0, e] = ti.min(k, self.capacity)

    @ti.kernel
    def _place(self, total: ti.i32, cdf: ti.template(), by_cell: ti.template()):
        """``total`` particles per member, uniform in the domain; or (``by_cell``) each in the first
        cell whose cumulative share ``cdf`` exceeds a uniform (bisection over the cells in C order),
        uniform within it."""
        key = ti.math.uvec2(self.key[0], self.key[1])
        self.overflow[None] = 0
        if total > self.capacity:
            self.overflow[None] = 1
        for e, k in ti.ndrange(self.ensemble, self.capacity):
            if k < total:
                r = rng.philox4x32(ti.math.uvec4(ti.u32(k), 0, self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
                y = ti.Vector.zero(self.real, self.dim)
                if ti.static(by_cell):
                    u = rng.uniform(r[3], ti.f64)
                    lo, hi = 0, cdf.shape[0] - 1
                    while lo < hi:
                        mid = (lo + hi) // 2
                        if cdf[mid] > u:
                            hi = mid
                        else:
                            lo = mid + 1
                    C = ti.Vector.zero(ti.i32, self.dim)
                    for b in ti.static(range(self.dim)):
                        a = ti.static(self.dim - 1 - b)
                        C[a] = lo % self.n[a]
                        lo //= self.n[a]
                    y = self.walker.in_cell(C, r, ti.Vector.zero(self.real, self.dim))
                else:
                    for a in ti.static(range(self.dim)):
                        y[a] = rng.uniform(r[a], self.real) * self.real(self.grid.lengths[a])
                self.pool.x[0, e, k] = y
        for e in range(self.ensemble):
            self.pool.n[0, e] = ti.min(total, self.capacity)


@ti.data_oriented
class ParticleSolver(Placement, Solver):
    r"""Brownian walkers with D = ½ for every ensemble member (paper §3, the particle model).

    One step moves each particle by the step of :meth:`Walker.move` (drawn there as ``bits``,
    ``own``, ``step_with``, :func:`rng.lanes` counter groups per loop iteration), so a particle
    crosses at most one cell per step and its path never depends on which thread moves it. Walls: periodic
    sides wrap, Neumann sides reflect, Dirichlet sides absorb what leaves and inject what a
    reservoir ghost layer at the reservoir density (sampled afresh each step) walks in.

    Particles live in a :class:`pools.ParticlePool`, member ``e`` in slots ``[0, n[cur, e])``. With
    Dirichlet sides a particle carries an id (slot at birth, birth step + 1), because absorption
    compacts the slots (:meth:`pools.ParticlePool.compact`, into the pool's other buffer);
    otherwise the slot is the id and one buffer suffices.

    Build it with :func:`ti_dk.make_solver`, which also initialises it.

    Parameters
    ----------
    grid, dt, ensemble, key, real, member0
        As for :class:`~ti_dk.methods.fv.SPDESolver`.
    capacity : int
        Particle slots per member (:meth:`capacity_for`); a step that needs more raises
        ``OverflowError``.
    """

    def __init__(self, grid: Grid, dt: float, ensemble: int, key: tuple[int, int], real, capacity: int,
                 member0: int = 0):
        self.grid, self.dt, self.ensemble, self.real, self.capacity = grid, dt, ensemble, real, capacity
        self.dim = grid.dim
        self.n = grid.cells
        self.key = key  # the Philox key of the run (rng.seed_key of its seed)
        self.walker = Walker(grid, dt, real, key, member0)
        open_ = grid.has_dirichlet
        self.pool = pools.ParticlePool(ensemble, capacity, self.dim, real, buffers=1, ids=open_)
        self.cur = 0  # the pool buffer holding the particles
        self.count = ti.field(ti.i32, shape=(ensemble, *self.n))  # particles per cell (after bin())
        self.clamped = ti.field(ti.i64, shape=())  # axis steps clamped to ±Δx in the last step
        self.inflow = ti.field(ti.i64, shape=())  # particles injected minus absorbed in the last step
        self.overflow = ti.field(ti.i32, shape=())  # set when a member needed more than `capacity` slots
        if open_:
            # reservoir ghost layer beyond each side of axis a: one cell thick
            self.layers = [tuple(1 if b == a else m for b, m in enumerate(self.n)) for a in range(self.dim)]
            self.cross = max(math.prod(layer) for layer in self.layers)

    @staticmethod
    def capacity_for(grid: Grid, ppc: np.ndarray) -> int:
        """Slots per member: the most particles sampling ``ppc`` can give; with reservoirs, room
        (:func:`pools.capacity`) for that or a domain full at the reservoir density."""
        cap = int(np.ceil(ppc).sum())
        if grid.has_dirichlet:
            cap = pools.capacity(max(cap, grid.reservoir_ppc_max * math.prod(grid.cells)))
        return max(cap, 1)

    # -- public -------------------------------------------------------------------------
    def initialize(self, ppc: np.ndarray, exact_uniform: bool = False, exact: bool = False) -> None:
        """Sample particles: ``ppc`` per cell as ℓ plus one with probability α (mean ℓ + α), uniform
        in the cell; or, with ``exact_uniform``, N = Σ ppc particles uniform in the whole domain
        (the exact equilibrium of a closed box); or, with ``exact``, N = round(Σ ppc) particles
        each in a cell drawn with probability ppc_I / Σ ppc, uniform in it (a fixed total, as
        closed walls keep it: the counts are multinomial)."""
        self.cur = 0
        if exact_uniform or exact:
            cdf = ti.field(ti.f64, shape=ppc.size)  # each cell's cumulative share (exact)
            cdf.from_numpy(np.cumsum(ppc.ravel()) / max(ppc.sum(), 1e-300))
            self._place(int(round(ppc.sum())), cdf, exact)
        else:
            f = ti.field(ti.f64, shape=self.n)
            f.from_numpy(np.ascontiguousarray(ppc, dtype=np.float64))
            self._sample(f)
        if self.grid.has_dirichlet:
            self._init_ids()
        self._check_overflow()

    def step(self, n: int) -> None:
        """Walk every particle from step ``n`` to ``n + 1``."""
        self._walk(self.cur, n)
        if self.grid.has_dirichlet:  # drop the absorbed, then inject from the reservoirs
            self.pool, self.cur = self.pool.compacted(self.cur)
            self._inject(self.cur, n)
            self._check_overflow()

    def state(self) -> dict[str, np.ndarray]:
        """The particles a checkpoint needs to continue bit for bit."""
        b = self.cur
        st = {"x": self.pool.x.to_numpy()[b], "n_alive": self.pool.n.to_numpy()[b]}
        return st | ({"pid": self.pool.pid.to_numpy()[b]} if self.grid.has_dirichlet else {})

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """Continue from a :meth:`state` (positions, counts, and the ids with Dirichlet sides)."""
        self.pool.load(st["x"][None], st["pid"][None] if self.grid.has_dirichlet else None, st["n_alive"][None])
        self.cur = 0

    def density(self) -> np.ndarray:
        """Number density of every member, ``(ensemble, *cells)``: counts / V_c, float64."""
        self._bin(self.cur)
        return self.count.to_numpy().astype(np.float64) / self.grid.cell_volume

    def content(self) -> tuple:
        """The particles binned per cell, 1, no region (:meth:`Solver.content`)."""
        self._bin(self.cur)
        return self.count, 1.0, None

    def diagnostics(self) -> dict[str, float]:
        """After the last step: the particles, the Dirichlet inflow and the clamped axis steps."""
        return {
            "mass": float(pools.total(self.pool.n, (self.cur,))),
            "min_density": math.nan,  # not binned every step; counts are never negative
            "negative_cells": 0,
            "boundary_inflow": float(self.inflow[None]),
            "clamped_steps": int(self.clamped[None]),
        }

    def _check_overflow(self) -> None:
        if self.overflow[None]:
            raise OverflowError(
                f"a member needed more than {self.capacity} particle slots: lower the densities or the reservoir_ppc"
            )

    # -- kernels ------------------------------------------------------------------------
    @ti.kernel
    def _init_ids(self):
        for e, k in ti.ndrange(self.ensemble, self.capacity):
            self.pool.pid[0, e, k] = ti.math.uvec2(ti.u32(k), 0)

    @ti.kernel
    def _walk(self, b: ti.i32, step: ti.u32):
        """Move the particles of buffer ``b``; with Dirichlet sides mark the absorbed as not kept."""
        self.clamped[None] = 0
        self.inflow[None] = 0
        G = ti.static(self.walker.group)
        x = ti.static(self.pool.x)
        if ti.static(self.grid.has_dirichlet):  # identities are not slots: one counter per particle
            for u in range(self.pool.units(b)):  # over the particles, not the capacity (pools.ParticlePool.units)
                e, U, lo, hi = self.pool.unit(b, u)
                for k in range(self.walker.rounds(lo, hi)):
                    for I, _ident, _x, y, alive, clamped, own in ti.static(
                            self.walker.lanes_at(self.pool, b, U, e, lo, hi, k, step)):
                        if own:
                            x[I] = y
                            if clamped:  # rare: an atomic for every particle would cost more than the step
                                self.clamped[None] += clamped
                            self.pool.keep[e, I[2]] = ti.u8(alive)
                            if not alive:
                                self.inflow[None] -= 1
        else:  # identity = slot: the G particles of a counter group walk together
            L = ti.static(self.walker.lanes)
            for e, k in ti.ndrange(self.ensemble, -(-self.capacity // (L * G))):
                n = self.pool.n[b, e]
                if L * G * k < n:  # L counter groups at once, their Philox calls first
                    bits = [self.walker.bits(e, ti.u32(G * (L * k + l)), ti.u32(0), step) for l in ti.static(range(L))]
                    for g in ti.static(range(G)):
                        ps = [G * (L * k + l) + g for l in ti.static(range(L))]
                        moved = [self.walker.step_with(x[b, e, ti.min(ps[l], self.capacity - 1)], bits[l], g)
                                 for l in ti.static(range(L))]
                        for l in ti.static(range(L)):
                            if ps[l] < n:
                                x[b, e, ps[l]] = moved[l][0]
                                if moved[l][2]:
                                    self.clamped[None] += moved[l][2]

    @ti.kernel
    def _inject(self, b: ti.i32, step: ti.u32):
        """Dirichlet sides: append to buffer ``b`` the reservoir walkers of step ``step`` that walk in."""
        key = ti.math.uvec2(self.key[0], self.key[1])
        K = ti.static(int(self.grid.reservoir_ppc_max) + 1)  # most particles a reservoir cell can hold
        for e in range(self.ensemble):
            j = self.pool.n[b, e]
            for a in ti.static(range(self.dim)):
                for side in ti.static(range(2)):
                    if ti.static(self.grid.boundary[a][side] == DIRICHLET):
                        lam = ti.static(self.grid.reservoir[a][side] * self.grid.cell_volume)
                        layer = ti.static(self.layers[a])
                        tag = ti.static((2 * a + side) * self.cross)
                        for G in ti.grouped(ti.ndrange(*layer)):
                            C = G
                            C[a] = -1 if side == 0 else self.n[a]
                            lin = ti.u32(0)
                            for c in ti.static(range(self.dim)):
                                lin = lin * ti.u32(layer[c]) + ti.u32(G[c])
                            lin += ti.u32(tag)
                            bits = rng.philox4x32(ti.math.uvec4(lin, step, self.walker.member(e), ti.u32(rng.SAMPLE_COUNT)), key)
                            m = self.walker.how_many(lam, bits[0])
                            for k in range(m):
                                id0 = lin * ti.u32(K) + ti.u32(k)
                                r = rng.philox4x32(
                                    ti.math.uvec4(id0, step, self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
                                y, alive, clamped = self.walker.move(self.walker.in_cell(C, r, ti.Vector.zero(self.real, self.dim)), e, id0, step + 1, step)
                                self.clamped[None] += clamped
                                if alive:
                                    if j < self.capacity:
                                        self.pool.x[b, e, j] = y
                                        self.pool.pid[b, e, j] = ti.math.uvec2(id0, step + 1)
                                        j += 1
                                        self.inflow[None] += 1
                                    else:
                                        self.overflow[None] = 1
            self.pool.n[b, e] = j

    @ti.kernel
    def _bin(self, b: ti.i32):
        for J in ti.grouped(self.count):
            self.count[J] = 0
        for e, p in ti.ndrange(self.ensemble, self.capacity):
            if p < self.pool.n[b, e]:
                J = ti.Vector.zero(ti.i32, self.dim + 1)
                J[0] = e
                for a in ti.static(range(self.dim)):
                    J[a + 1] = cell_of(self.pool.x[b, e, p][a], self.real(self.grid.dx[a]), self.n[a])
                self.count[J] += 1
