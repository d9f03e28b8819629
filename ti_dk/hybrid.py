"""The AMAR hybrid (paper §3): the SPDE everywhere, real Brownian particles in a particle region."""

import itertools
import math
import time

import numpy as np
import taichi as ti

from . import regrid, rng
from .config import HYBRID_STEP_LIMIT, ID_BITS_MIN
from .fv import SPDESolver
from .grid import DIRICHLET, PERIODIC, cell_of, numpy_dtype
from .particles import Walker

BLOCK = 256  # slots per compaction block: an exclusive scan over blocks replaces a contended atomic
REGRID_BIRTH = HYBRID_STEP_LIMIT  # flag in the birth word of particles sampled at a regrid (ghosts: step + 1)
TOO_MANY = 2**31 - 1  # `need` when a cell asked for more particles than an id can number
# one record per regrid; on_demand: members regridded off schedule (0: a scheduled regrid of all)
REGRID_LOG = ("step", "boxes", "covered_cells", "efficiency", "created", "removed", "on_demand")


def _clock() -> float:
    """Seconds, after the device has finished what was launched (kernels may run asynchronously)."""
    ti.sync()
    return time.perf_counter()


@ti.data_oriented
class ParticlePool:
    """The particles of every member, double-buffered: buffer ``b`` of member ``e`` holds slots
    ``[0, n[b, e])``. A step reads one buffer and compacts into the other; when a member needs
    more than ``capacity`` slots the solver replaces the pool by a larger one."""

    def __init__(self, ensemble: int, capacity: int, dim: int, real):
        self.capacity = capacity
        self.blocks = -(-capacity // BLOCK)  # compaction blocks per member
        self.x = ti.Vector.field(dim, real, shape=(2, ensemble, capacity))  # positions [length]
        # identity: (birth cell · 2^id_bits + index in that cell, birth word); keys the walk
        self.pid = ti.Vector.field(2, ti.u32, shape=(2, ensemble, capacity))
        self.n = ti.field(ti.i32, shape=(2, ensemble))  # occupied slots per buffer and member
        self.keep = ti.field(ti.u8, shape=(ensemble, capacity))  # 1: the slot survives the compaction
        self.offset = ti.field(ti.i32, shape=(ensemble, self.blocks))  # first target slot of each block
        self.top = ti.field(ti.i32, shape=())  # most occupied slots of any member in the buffer being walked


@ti.data_oriented
class HybridSolver:
    r"""SPDE on the whole grid coupled to particles in a region (paper §3.1–3.2).

    One step ``n → n+1``:

    1. the ghost ring (cells outside the region within Chebyshev distance 1 of it, and Dirichlet
       reservoir cells beyond covered boundary cells) gets ``ℓ`` particles plus one with
       probability ``α``, where ``ℓ + α = max(q_I^n, 0) V_c`` (paper §3), placed with the linear
       profile of :meth:`_tilt` (the slope of the deterministic q̄, by default);
    2. the SPDE advances everywhere, eq. (9), giving ``q^{n+1,*}`` and the face fluxes ``F``;
    3. every particle (real and ghost) takes one clamped step (:class:`Walker`); those ending in
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

    The region is a cell mask per member, so the result does not depend on how it is cut into
    boxes, and a particle's random numbers depend only on its identity (birth cell, index, birth
    step), never on its slot. With a fixed region and periodic or Neumann walls, the total number
    of particles (SPDE mass plus particles) is conserved to round-off.

    Regridding (every ``regrid_interval`` steps, at the start, and on demand for a member that
    starts a step with an uncovered cell below the threshold; 0 keeps the first region): tag,
    buffer and Berger–Rigoutsos per member; particles in cells that stay covered are kept, cells
    that leave the region keep their count as density, newly covered cells are sampled from the
    SPDE (the only step that changes the total; logged in ``regrids``). At the start the state is
    the piecewise-constant initial condition, so those particles lie uniformly in their cells.
    """

    def __init__(self, spde: SPDESolver, params: regrid.RegridParams, regrid_interval: int, seed: int,
                 ghost_profile: str = "mean", substeps: int = 1):
        grid = spde.grid
        self.profile, self.substeps = ghost_profile, substeps
        self.spde, self.params, self.regrid_interval = spde, params, regrid_interval
        self.grid, self.dt, self.ensemble, self.real = grid, spde.dt, spde.ensemble, spde.real
        self.dim, self.n = grid.dim, grid.cells
        self.key = rng.seed_key(seed)
        self.walker = Walker(grid, spde.dt / substeps, spde.real, seed, spde.member0)  # one particle sub-step
        assert ghost_profile != "mean" or spde.track_mean, "ghost_profile 'mean' reads the SPDE's q̄"
        if substeps > 1:
            self.q_old = ti.field(spde.real, shape=(spde.ensemble, *grid.cells))  # q^n while q holds q^{n+1,*} [1/volume]
        self.offsets = list(itertools.product((-1, 0, 1), repeat=self.dim))  # the 3^d Chebyshev neighbours
        self.padded = tuple(m + 2 for m in self.n)  # the grid plus one layer of ghost cells per side
        self.id_bits = 32 - math.ceil(math.log2(math.prod(self.padded)))
        assert self.id_bits >= ID_BITS_MIN, "config.make_scene refuses such grids"
        self.periodic = tuple(lo == PERIODIC for lo, _ in grid.boundary)
        E, n = self.ensemble, self.n
        self.covered = ti.field(ti.u8, shape=(E, *n))  # 1 where the cell is in the particle region
        self.fresh = ti.field(ti.u8, shape=(E, *n))  # the region being regridded to
        self.low = ti.field(ti.u8, shape=(E, *n))  # 1: uncovered, and too low to stay so (_mark_low)
        self.ring = ti.field(ti.u8, shape=(E, *self.padded))  # 1 on ghost cells (padded index = cell + 1)
        self.ring_list = ti.field(ti.i32, shape=E * math.prod(self.padded))  # flat indices of ghost cells
        self.cover_list = ti.field(ti.i32, shape=E * math.prod(n))  # flat indices of covered cells
        self.n_ring, self.n_cover = 0, 0  # lengths of the two lists
        self.count = ti.field(ti.i32, shape=(E, *n))  # particles ending the walk in each covered cell
        self.dN = ti.field(ti.i32, shape=(E, *n))  # ΔN: net particles the region gave each uncovered cell
        self.entered = ti.field(ti.u64, shape=(E, *n))  # bit k: ghost k of this cell walked into the region
        self.cap = ti.field(ti.i32, shape=(E, *n))  # most ghosts of this cell that may enter this sub-step
        self.n_real = ti.field(ti.i32, shape=E)  # particles of each member between steps
        self.need = ti.field(ti.i32, shape=())  # most slots a member asked for (TOO_MANY: a cell overflowed)
        self.clamped = ti.field(ti.i64, shape=())  # axis steps clamped to ±Δx in the last walk
        self.p_inflow = ti.field(ti.i64, shape=())  # particles injected minus absorbed at Dirichlet sides
        self.wall_inflow = ti.field(ti.f64, shape=())  # SPDE boundary inflow of covered cells (cancelled)
        self.created = ti.field(ti.i64, shape=())  # particles sampled at the last regrid
        self.removed = ti.field(ti.f64, shape=())  # SPDE content Σ q V_c those cells held before
        self.pool = ParticlePool(E, 1, self.dim, self.real)
        self.cur = 0  # the pool buffer holding the particles between steps
        self.boxes: list[list[regrid.Box]] = [[] for _ in range(E)]  # each member's region
        self.regrids: list[dict] = []  # one record per regrid
        self._change = 0.0  # created − removed at this step's regrid
        self.timing = {"spde": 0.0, "particles": 0.0, "regrid": 0.0}  # seconds spent in each part

    # -- public -------------------------------------------------------------------------
    def initialize(self) -> None:
        """The first region from the (already initialised) SPDE, particles sampled into it."""
        self.regrid(0)

    def step(self, n: int) -> None:
        """Advance from step ``n`` to ``n + 1`` (see the class docstring)."""
        self._change = 0.0
        if self.regrid_interval and n > 0:
            t = _clock()
            if n % self.regrid_interval == 0:
                self.regrid(n)
            elif self.params.floor > 0 and self._mark_low(self.params.floor * self.params.threshold):
                self.extend(n)
            self.timing["regrid"] += _clock() - t
        t0 = _clock()
        if self.n_cover == 0:  # no particle region: a plain SPDE step
            self.spde.step(n)
            self.timing["spde"] += _clock() - t0
            return
        tilt_on = self._tilt_on(n)
        k = self.substeps
        if k > 1:
            self.q_old.copy_from(self.spde.q)
        self._fill_ghosts(n * k, 0.0, tilt_on)
        t1 = _clock()
        self.spde.fluxes(n)
        self.spde.update()
        t2 = _clock()
        self._s1(self.n_ring)
        self.clamped[None] = 0
        self.p_inflow[None] = 0
        for s in range(k):  # particle sub-steps of Δt/k; ghosts from q interpolated in time
            if s > 0:
                self._fill_ghosts(n * k + s, s / k, 1)
            self._walk(self.pool, self.cur, n * k + s, int(s == k - 1))
            self._cap_entries(self.pool, self.cur, n * k + s, int(s == k - 1), self.n_ring)
            self._compact(self.pool, self.cur)
            self.cur = 1 - self.cur
        self._sync(self.n_cover, self.n_ring)
        self.spde.diagnose()
        t3 = _clock()
        self.timing["spde"] += t2 - t1
        self.timing["particles"] += (t1 - t0) + (t3 - t2)

    def _tilt_on(self, n: int) -> int:
        """Whether particles sampled at step ``n`` are tilted: not at the start with ``mean``, where
        q̄ is the piecewise-constant initial condition (particles lie uniformly in each cell)."""
        return int(self.profile != "mean" or n > 0)

    def _fill_ghosts(self, sub: int, w: float, tilt_on: int) -> None:
        """Ghosts for particle sub-step ``sub`` from ``(1 − w) q^n + w q^{n+1,*}`` (for s > 0 after S1,
        :meth:`_s1`: what the SPDE left in the ghost cell); the fill is a pure
        function of its inputs, so a pool that is too small is grown and the fill redone."""
        while True:
            self._fill(self.pool, self.cur, sub, self.n_ring, w, tilt_on)
            need = self._check_need()
            if need <= self.pool.capacity:
                return
            self._grow(2 * need)
            self._drop_ghosts(self.pool, self.cur)

    def regrid(self, n: int) -> None:
        """New region from the SPDE density at step ``n`` (tag, buffer, Berger–Rigoutsos)."""
        ppc = self.spde.density() * self.grid.cell_volume
        tags = regrid.grow(regrid.tag(ppc, self.params.threshold), self.params.buffer, (None, *self.periodic))
        masks = np.zeros(ppc.shape, dtype=bool)
        cache: dict[bytes, tuple] = {}  # members with the same tags get the same boxes
        for e in range(self.ensemble):
            k = tags[e].tobytes()
            if k not in cache:
                cache[k] = regrid.cluster(tags[e], self.params)
            self.boxes[e] = cache[k]
            masks[e] = regrid.mask(self.boxes[e], self.n)
        self.set_region(masks, n, ppc)
        self._log(n, int(tags.sum()), 0)

    def extend(self, n: int) -> None:
        """Cover, before step ``n``, the cells :meth:`_mark_low` marked (grown by the buffer,
        clustered by Berger–Rigoutsos) and keep the rest of the region: the on-demand regrid.

        Tagging promises that no uncovered cell holds fewer than ``threshold`` particles; between
        scheduled regrids that promise breaks, and FV then goes negative (one 2D step at C = 1/16
        moves about √N/2 particles). Keeping it at every step (``regrid_floor = 1``) together with
        the ghost-entry cap of :meth:`_cap_entries` cut the negative cell-steps of the default
        ellipse2d run from 47 to 1 (an FV step of 4.7 σ from 5.6 particles); the cap alone to 8.
        The price is an extension on most steps of that run (about 2× its time): ``regrid_floor``
        is the knob.
        """
        ppc = self.spde.density() * self.grid.cell_volume
        masks = self.region()
        low = self.low.to_numpy().astype(bool)
        add = regrid.grow(low, self.params.buffer, (None, *self.periodic))
        members = np.flatnonzero(low.reshape(self.ensemble, -1).any(axis=1))
        for e in members:
            boxes = regrid.cluster(add[e], self.params)
            self.boxes[e] = list(self.boxes[e]) + boxes
            masks[e] |= regrid.mask(boxes, self.n)
        self.set_region(masks, n, ppc)
        self._log(n, int(regrid.tag(ppc, self.params.threshold).sum()), len(members))

    def _log(self, n: int, tagged: int, on_demand: int) -> None:
        covered = self.n_cover
        self.regrids.append({"step": n, "boxes": sum(len(b) for b in self.boxes), "covered_cells": covered,
                             "efficiency": tagged / covered if covered else 1.0,
                             "created": int(self.created[None]), "removed": float(self.removed[None]),
                             "on_demand": on_demand})

    def set_region(self, masks: np.ndarray, n: int, ppc: np.ndarray | None = None) -> None:
        """Make ``masks`` (``(ensemble, *cells)`` booleans) the particle region at step ``n``."""
        if ppc is None:
            ppc = self.spde.density() * self.grid.cell_volume
        masks = np.broadcast_to(masks, (self.ensemble, *self.n))
        self._grow(self._estimate(masks, ppc))
        self.fresh.from_numpy(masks.astype(np.uint8))
        tilt_on = self._tilt_on(n)
        self._regrid_apply(self.pool, self.cur, n * self.substeps, tilt_on)
        self._compact(self.pool, self.cur)
        self.cur = 1 - self.cur
        self._lists()
        if self._check_need() > self.pool.capacity:  # the estimate bounds it; kept as a guard
            raise RuntimeError("particle pool estimate too small at a regrid")
        self._change += self.created[None] - self.removed[None]
        self.spde.diagnose()

    def state(self) -> dict[str, np.ndarray]:
        """SPDE fields, region, boxes, regrid log and the particles (compacted, with their ids)."""
        n = self.n_real.to_numpy()
        top = max(1, int(n.max()))
        boxes = [(e, *lo, *hi) for e, bs in enumerate(self.boxes) for lo, hi in bs]
        st = {f"spde_{k}": v for k, v in self.spde.state().items()}
        st |= {"covered": self.covered.to_numpy(), "n_real": n,
               "x": self.pool.x.to_numpy()[self.cur, :, :top], "pid": self.pool.pid.to_numpy()[self.cur, :, :top],
               "boxes": np.array(boxes, dtype=np.int64).reshape(-1, 1 + 2 * self.dim)}
        for k in REGRID_LOG:
            st[f"regrid_{k}"] = np.array([r[k] for r in self.regrids])
        return st

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        self.spde.load_state({k[5:]: v for k, v in st.items() if k.startswith("spde_")})
        n, x, pid = st["n_real"], st["x"], st["pid"]
        self._grow(max(self.pool.capacity, int(1.5 * x.shape[1]) + 64))
        cap = self.pool.capacity
        px = np.zeros((2, self.ensemble, cap, self.dim), dtype=numpy_dtype(self.real))
        ppid = np.zeros((2, self.ensemble, cap, 2), dtype=np.uint32)
        px[0, :, :x.shape[1]], ppid[0, :, :x.shape[1]] = x, pid
        self.pool.x.from_numpy(px)
        self.pool.pid.from_numpy(ppid)
        self.pool.n.from_numpy(np.stack([n, np.zeros_like(n)]).astype(np.int32))
        self.n_real.from_numpy(n.astype(np.int32))
        self.cur = 0
        self.covered.from_numpy(st["covered"])
        self._lists()
        self.boxes = [[] for _ in range(self.ensemble)]
        for row in st["boxes"]:
            self.boxes[row[0]].append((tuple(int(v) for v in row[1:1 + self.dim]), tuple(int(v) for v in row[1 + self.dim:])))
        self.regrids = [{k: st[f"regrid_{k}"][i].item() for k in REGRID_LOG} for i in range(len(st["regrid_step"]))]

    def density(self) -> np.ndarray:
        return self.spde.density()

    def region(self) -> np.ndarray:
        """The particle region of every member, ``(ensemble, *cells)`` booleans."""
        return self.covered.to_numpy().astype(bool)

    def diagnostics(self) -> dict[str, float]:
        d = self.spde.diagnostics()
        if self.n_cover:  # otherwise the last step was a plain SPDE step
            d["boundary_inflow"] = d["boundary_inflow"] + self.wall_inflow[None] + self.p_inflow[None]
            d["clamped_steps"] = int(self.clamped[None])
        d["particles"] = int(self.n_real.to_numpy().sum(dtype=np.int64))
        d["regrid_change"] = self._change
        return d

    # -- pool management (host) ---------------------------------------------------------
    def _estimate(self, masks: np.ndarray, ppc: np.ndarray) -> int:
        """Slots a member can need after a regrid: its region and ghost ring full, with headroom."""
        axes = tuple(range(1, self.dim + 1))
        now = self.covered.to_numpy().astype(bool)  # particles of the old region are still in the pool
        near = regrid.grow(masks, 1, (None, *self.periodic)) | now
        inside = np.ceil(np.maximum(ppc, 0) * near).sum(axis=axes)
        walls = self.grid.reservoir_ppc_max * 3 ** (self.dim - 1) * masks.sum(axis=axes) if self.grid.has_dirichlet else 0
        need = float(np.max(inside + walls)) if self.ensemble else 0.0
        return int(1.5 * need + 4 * math.sqrt(need) + 64)

    def _lists(self) -> None:
        """Ghost ring and the flat lists of ring and covered cells, from ``covered``."""
        self._ring()
        self.n_ring = self._list(self.ring, self.ring_list)
        self.n_cover = self._list(self.covered, self.cover_list)

    @staticmethod
    def _list(flags, out) -> int:
        """Write the flat indices of the nonzero ``flags`` to the front of ``out``; return how many."""
        idx = np.flatnonzero(flags.to_numpy()).astype(np.int32)
        buf = np.zeros(out.shape, dtype=np.int32)
        buf[:idx.size] = idx
        out.from_numpy(buf)
        return int(idx.size)

    def _check_need(self) -> int:
        need = self.need[None]
        if need == TOO_MANY:
            raise OverflowError(
                f"a ghost or newly covered cell holds more than {2**self.id_bits - 1} particles: "
                "lower the density or use fewer cells")
        return int(need)

    def _grow(self, capacity: int) -> None:
        """Replace the pool by one of at least ``capacity`` slots, keeping the current particles."""
        old = self.pool
        if capacity <= old.capacity:
            return
        capacity = max(capacity, 2 * old.capacity)  # geometric: every new pool recompiles the kernels
        new = ParticlePool(self.ensemble, capacity, self.dim, self.real)
        x, pid = old.x.to_numpy(), old.pid.to_numpy()
        nx = np.zeros((2, self.ensemble, capacity, self.dim), dtype=numpy_dtype(self.real))
        npid = np.zeros((2, self.ensemble, capacity, 2), dtype=np.uint32)
        nx[:, :, :old.capacity], npid[:, :, :old.capacity] = x, pid
        new.x.from_numpy(nx)
        new.pid.from_numpy(npid)
        new.n.from_numpy(old.n.to_numpy())
        self.pool = new

    # -- numerics (ti.func) -------------------------------------------------------------
    @ti.func
    def _member(self, e, C):
        """The member-first index ``(e, *C)``."""
        J = ti.Vector.zero(ti.i32, self.dim + 1)
        J[0] = e
        for a in ti.static(range(self.dim)):
            J[a + 1] = C[a]
        return J

    @ti.func
    def _unflatten(self, i, shape: ti.template()):
        """The index vector of flat (C-order) index ``i`` in an array of ``shape``."""
        d = ti.static(len(shape))
        J = ti.Vector.zero(ti.i32, d)
        for b in ti.static(range(d)):
            a = ti.static(d - 1 - b)
            J[a] = i % shape[a]
            i //= shape[a]
        return J

    @ti.func
    def _inside(self, C) -> bool:
        ok = True
        for a in ti.static(range(self.dim)):
            ok = ok and 0 <= C[a] < self.n[a]
        return ok

    @ti.func
    def _origin(self, id0):
        """The birth cell of a particle (it may be a reservoir cell, one layer outside)."""
        lin = ti.cast(id0 >> ti.u32(self.id_bits), ti.i32)
        C = ti.Vector.zero(ti.i32, self.dim)
        for b in ti.static(range(self.dim)):
            a = ti.static(self.dim - 1 - b)
            C[a] = lin % self.padded[a] - 1
            lin //= self.padded[a]
        return C

    @ti.func
    def _profile(self, J):
        """The density the ghost tilts are read from at member-first index ``J``: q̄ (``mean``) or q."""
        v = self.real(0.0)
        if ti.static(self.profile == "mean"):
            J0 = J
            J0[0] = 0
            v = self.spde.qbar[J0]
        else:
            v = self.spde.q[J]
        return v

    @ti.func
    def _tilt(self, e, C):
        r"""Linear profile of cell ``C`` for :meth:`Walker.in_cell`: ``b_a = (p_{C+e_a} − p_{C−e_a}) / (2 p_C)``
        clipped to [−2, 2] so the density stays ≥ 0: the centred slope of the profile density ``p``
        (a Neumann side mirrors, a Dirichlet side sees its reservoir). Zero with ``ghost_profile = 'uniform'``.

        Which ``p`` (``ghost_profile``), measured on the paper's void case (benchmarks/RESULTS.md):

        - ``uniform`` (paper §3): ``b = 0``. Near a density gradient the particles of a ghost cell do
          not lie uniformly; uniform placement puts too many next to the low side and biases the
          mean of the cells on both sides of the interface (6–12 standard errors).
        - ``linear``: ``p = q`` of the member. The slope of a ghost cell next to the region reads the
          covered neighbour's particle count, so the inflow grows with the region's own
          fluctuation: positive feedback, variance of the first covered cells 8 % too high.
        - ``mean`` (default): ``p = q̄``, the deterministic scheme (eq. 10) advanced alongside, the
          same for every member: the profile of the ensemble mean, with no feedback from any
          member's fluctuation. The count still comes from the member's own ``q``.
        """
        b = ti.Vector.zero(self.real, self.dim)
        if ti.static(self.profile != "uniform"):
            J = self._member(e, C)
            qc = self._profile(J)
            for a in ti.static(range(self.dim)):
                lo, hi = J, J
                lo[a + 1] -= 1
                hi[a + 1] += 1
                q_lo, q_hi = qc, qc
                if ti.static(self.periodic[a]):
                    lo[a + 1] = (lo[a + 1] + self.n[a]) % self.n[a]
                    hi[a + 1] = hi[a + 1] % self.n[a]
                    q_lo, q_hi = self._profile(lo), self._profile(hi)
                else:
                    if C[a] > 0:
                        q_lo = self._profile(lo)
                    elif ti.static(self.grid.boundary[a][0] == DIRICHLET):
                        q_lo = self.real(self.grid.reservoir[a][0])
                    if C[a] < self.n[a] - 1:
                        q_hi = self._profile(hi)
                    elif ti.static(self.grid.boundary[a][1] == DIRICHLET):
                        q_hi = self.real(self.grid.reservoir[a][1])
                if qc > 0:
                    b[a] = ti.math.clamp((q_hi - q_lo) / (self.real(2.0) * qc), self.real(-2.0), self.real(2.0))
        return b

    @ti.func
    def _sample(self, pool: ti.template(), buf, e, C, lam, step, birth, tilt_on):
        """Append ℓ particles plus one with probability α (``lam = ℓ + α``) to cell ``C`` (paper §3),
        placed by :meth:`_tilt` (uniform where ``tilt_on`` is 0), in buffer ``buf`` of member ``e``;
        returns how many."""
        lin = ti.u32(0)
        for a in ti.static(range(self.dim)):
            lin = lin * ti.u32(self.padded[a]) + ti.u32(C[a] + 1)
        key = ti.math.uvec2(self.key[0], self.key[1])
        bits = rng.philox4x32(ti.math.uvec4(lin, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_COUNT)), key)
        m = self.walker.how_many(ti.max(lam, 0.0), bits[0])
        if m >= (1 << self.id_bits):
            ti.atomic_max(self.need[None], TOO_MANY)
            m = 0
        base = ti.atomic_add(pool.n[buf, e], m)
        ti.atomic_max(self.need[None], base + m)
        tilt = ti.Vector.zero(self.real, self.dim)
        if m > 0 and tilt_on and self._inside(C):
            tilt = self._tilt(e, C)
        for k in range(m):
            if base + k < pool.capacity:
                id0 = (lin << ti.u32(self.id_bits)) | ti.u32(k)
                r = rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
                pool.x[buf, e, base + k] = self.walker.in_cell(C, r, tilt)
                pool.pid[buf, e, base + k] = ti.math.uvec2(id0, ti.u32(birth))
        return m

    # -- kernels ------------------------------------------------------------------------
    @ti.kernel
    def _ring(self):
        """Mark the ghost cells: not covered, within Chebyshev distance 1 of a covered cell."""
        for I in ti.grouped(self.ring):
            C = ti.Vector([I[a + 1] - 1 for a in ti.static(range(self.dim))])
            outside = 0
            ok = True
            for a in ti.static(range(self.dim)):  # outside cells only beyond Dirichlet sides
                if C[a] < 0:
                    outside += 1
                    if ti.static(self.grid.boundary[a][0] != DIRICHLET):
                        ok = False
                elif C[a] >= self.n[a]:
                    outside += 1
                    if ti.static(self.grid.boundary[a][1] != DIRICHLET):
                        ok = False
            r = 0
            if ok and outside <= 1 and not (outside == 0 and self.covered[self._member(I[0], C)]):
                for off in ti.static(self.offsets):
                    N = C + ti.Vector(off)
                    inside = True
                    for a in ti.static(range(self.dim)):
                        if ti.static(self.periodic[a]):
                            N[a] = (N[a] + self.n[a]) % self.n[a]
                        inside = inside and 0 <= N[a] < self.n[a]
                    if inside and self.covered[self._member(I[0], N)]:
                        r = 1
            self.ring[I] = ti.u8(r)

    @ti.kernel
    def _fill(self, pool: ti.template(), cur: ti.i32, step: ti.i32, n_ring: ti.i32, w: ti.f64, tilt_on: ti.i32):
        """Step 1: ghost particles appended after the real ones, from ``(1 − w) q^n + w q^{n+1,*}``
        (``w = s/k`` at particle sub-step s of k; q^n itself when k = 1) or the reservoir."""
        vol = ti.static(self.grid.cell_volume)
        self.need[None] = 0
        for i in range(n_ring):
            I = self._unflatten(self.ring_list[i], ti.static(self.ring.shape))
            C = ti.Vector([I[a + 1] - 1 for a in ti.static(range(self.dim))])
            lam = 0.0
            if self._inside(C):
                J = self._member(I[0], C)
                lam = ti.cast(self.spde.q[J], ti.f64)
                if ti.static(self.substeps > 1):
                    lam = (1.0 - w) * ti.cast(self.q_old[J], ti.f64) + w * lam
                lam *= vol
            else:
                for a in ti.static(range(self.dim)):
                    if C[a] < 0:
                        lam = self.grid.reservoir[a][0] * vol
                    elif C[a] >= self.n[a]:
                        lam = self.grid.reservoir[a][1] * vol
            self._sample(pool, cur, I[0], C, lam, step, step + 1, tilt_on)

    @ti.kernel
    def _mark_low(self, threshold: ti.f64) -> ti.i32:
        """Mark in ``low`` the uncovered cells below ``threshold`` particles (or negative), which
        :meth:`extend` covers; return how many (all members)."""
        vol = ti.static(self.grid.cell_volume)
        total = 0
        for J in ti.grouped(self.covered):
            low = 0
            if not self.covered[J] and ti.cast(self.spde.q[J], ti.f64) * vol < threshold:
                low = 1
            self.low[J] = ti.u8(low)
            total += low
        return total

    @ti.kernel
    def _drop_ghosts(self, pool: ti.template(), cur: ti.i32):
        for e in range(self.ensemble):
            pool.n[cur, e] = self.n_real[e]

    @ti.kernel
    def _walk(self, pool: ti.template(), cur: ti.i32, step: ti.i32, last: ti.i32):
        """Step 3 (one particle sub-step): walk, keep what ends in the region (compacted into the
        other buffer), add to ΔN; on the ``last`` sub-step count the particles per covered cell."""
        pool.top[None] = 0
        for e in range(self.ensemble):
            ti.atomic_max(pool.top[None], pool.n[cur, e])
        # over the occupied slots only: the pool is sized for regrids (≈ 2× the particles), and
        # a loop over its whole capacity spent ≈ 10 % of the walk testing empty slots
        for i in range(self.ensemble * pool.top[None]):
            e, p = 0, i
            if ti.static(self.ensemble > 1):
                e, p = i // pool.top[None], i % pool.top[None]
            if p < pool.n[cur, e]:
                ident = pool.pid[cur, e, p]
                y, alive, clamped = self.walker.move(pool.x[cur, e, p], e, ident[0], ident[1], ti.u32(step))
                if clamped:  # rare (p ≈ erfc(Δx/√(2Δt)) per axis): no atomic on the shared counter otherwise
                    self.clamped[None] += clamped
                ghost = ident[1] == ti.u32(step + 1)
                D = ti.Vector.zero(ti.i32, self.dim + 1)
                D[0] = e
                keep = False
                if alive:
                    for a in ti.static(range(self.dim)):
                        D[a + 1] = cell_of(y[a], self.real(self.grid.dx[a]), self.n[a])
                    keep = self.covered[D] != 0
                pool.x[cur, e, p] = y
                pool.keep[e, p] = ti.u8(keep)
                if keep:
                    counted = True
                    if ghost:
                        O = self._origin(ident[0])
                        if self._inside(O):
                            k = ident[0] & ti.u32((1 << self.id_bits) - 1)
                            if k < 64:  # settled by _cap_entries
                                ti.atomic_or(self.entered[self._member(e, O)], ti.u64(1) << ti.cast(k, ti.u64))
                                counted = False
                            else:
                                self.dN[self._member(e, O)] -= 1
                        else:
                            self.p_inflow[None] += 1
                    if last and counted:
                        self.count[D] += 1
                elif not ghost:
                    if alive:
                        self.dN[D] += 1
                    else:
                        self.p_inflow[None] -= 1

    @ti.kernel
    def _compact(self, pool: ti.template(), cur: ti.i32):
        """Copy the slots marked ``keep`` of buffer ``cur`` to the front of the other buffer, in
        order: per-block counts, an exclusive scan over blocks, then a scatter."""
        nxt = 1 - cur
        for e, b in ti.ndrange(self.ensemble, pool.blocks):
            c = 0
            for p in range(b * BLOCK, ti.min(b * BLOCK + BLOCK, pool.n[cur, e])):
                c += ti.cast(pool.keep[e, p], ti.i32)
            pool.offset[e, b] = c
        for e in range(self.ensemble):
            total = 0
            for b in range(pool.blocks):
                c = pool.offset[e, b]
                pool.offset[e, b] = total
                total += c
            pool.n[nxt, e] = total
            self.n_real[e] = total
        for e, b in ti.ndrange(self.ensemble, pool.blocks):
            j = pool.offset[e, b]
            for p in range(b * BLOCK, ti.min(b * BLOCK + BLOCK, pool.n[cur, e])):
                if pool.keep[e, p]:
                    pool.x[nxt, e, j] = pool.x[cur, e, p]
                    pool.pid[nxt, e, j] = pool.pid[cur, e, p]
                    j += 1

    @ti.kernel
    def _sync(self, n_cover: ti.i32, n_ring: ti.i32):
        """Step 4: covered cells take their counts; ring cells swap S1 fluxes for ΔN (eq. 12)."""
        self.wall_inflow[None] = 0.0
        for i in range(n_cover + n_ring):  # one parallel loop: covered cells, then ring cells
            if i < n_cover:
                self._take_count(self._unflatten(self.cover_list[i], ti.static(self.covered.shape)))
            else:
                J, inside = self._ring_cell(i - n_cover)
                if inside:
                    self._reflux(J)

    @ti.func
    def _take_count(self, J):
        """Synchronise covered cell ``J``: q = N / V_c."""
        vol = ti.static(self.grid.cell_volume)
        self.spde.q[J] = self.real(ti.cast(self.count[J], ti.f64) / vol)
        self.count[J] = 0
        if ti.static(self.grid.has_dirichlet):  # the SPDE's boundary flux of this cell did not happen
            for a in ti.static(range(self.dim)):
                area = ti.static(self.grid.face_area[a] * self.dt)
                if ti.static(self.grid.boundary[a][0] == DIRICHLET):
                    if J[a + 1] == 0:
                        self.wall_inflow[None] += ti.cast(self.spde.flux[J][a], ti.f64) * area
                if ti.static(self.grid.boundary[a][1] == DIRICHLET):
                    if J[a + 1] == self.n[a] - 1:
                        self.wall_inflow[None] -= ti.cast(self.spde.flux[self.spde.upper(J, a)][a], ti.f64) * area

    @ti.func
    def _ring_cell(self, i):
        """The member-first index of ring cell ``i`` of ``ring_list``, and whether it is in the domain."""
        P = self._unflatten(self.ring_list[i], ti.static(self.ring.shape))
        J = P - 1
        J[0] = P[0]
        return J, self._inside(ti.Vector([J[a + 1] for a in ti.static(range(self.dim))]))

    @ti.kernel
    def _s1(self, n_ring: ti.i32):
        r"""S1 of eq. (12), before the walk: each ghost cell ``I`` drops the terms ∓ Δt F / Δx_a that
        eq. (9) applied across its faces with covered cells, ``q_I ← q_I^{n+1,*} − Σ_{S1} F^{i→I}/V_c``,
        so that ``q_I`` holds what the SPDE leaves in it; S2 (``ΔN_I / V_c``) is added by :meth:`_sync`."""
        for i in range(n_ring):
            J, inside = self._ring_cell(i)
            if inside:
                corr = self.real(0.0)
                for a in ti.static(range(self.dim)):
                    u = ti.Vector.unit(self.dim + 1, a + 1, ti.i32)
                    lo, hi = J - u, J + u
                    has_lo, has_hi = J[a + 1] > 0, J[a + 1] < self.n[a] - 1
                    if ti.static(self.periodic[a]):
                        lo[a + 1] = (lo[a + 1] + self.n[a]) % self.n[a]
                        hi[a + 1] = hi[a + 1] % self.n[a]
                        has_lo, has_hi = True, True
                    k = self.real(self.dt / self.grid.dx[a])
                    # F is positive down the axis: F = ½ Δq/Δx + noise
                    if has_lo and self.covered[lo]:
                        corr += k * self.spde.flux[J][a]
                    if has_hi and self.covered[hi]:
                        corr -= k * self.spde.flux[self.spde.upper(J, a)][a]
                self.spde.q[J] += corr

    @ti.kernel
    def _cap_entries(self, pool: ti.template(), cur: ti.i32, step: ti.i32, last: ti.i32, n_ring: ti.i32):
        """Let at most ``⌊q_I V_c + ΔN_I⌋`` of the ghosts of cell ``I`` enter the region in this
        sub-step: the content the SPDE left in it (after S1) plus what the region gave it so far.
        Without this cap a ghost cell holding ``ℓ + α`` particles, ``ℓ + 1`` ghosts of which all
        walk in while its SPDE fluxes also carry content away, goes negative (measured: 6
        cell-steps in the default ellipse2d run, in cells holding 5–8 particles). The ghosts
        that enter are those of lowest index among the ones that walked in, so the result does
        not depend on thread order; cells with more than 64 ghosts are not capped (64 ghosts all
        walking in does not happen)."""
        vol = ti.static(self.grid.cell_volume)
        for i in range(n_ring):
            J, inside = self._ring_cell(i)
            if inside:
                room = ti.floor(ti.cast(self.spde.q[J], ti.f64) * vol + ti.cast(self.dN[J], ti.f64))
                cap = ti.cast(ti.max(room, 0.0), ti.i32)
                self.cap[J] = cap
                self.dN[J] -= ti.min(ti.cast(ti.math.popcnt(self.entered[J]), ti.i32), cap)
        for i in range(self.ensemble * pool.top[None]):  # the occupied slots (pool.top: set by _walk)
            e, p = 0, i
            if ti.static(self.ensemble > 1):
                e, p = i // pool.top[None], i % pool.top[None]
            if p < pool.n[cur, e] and pool.keep[e, p]:
                ident = pool.pid[cur, e, p]
                if ident[1] == ti.u32(step + 1):
                    O = self._origin(ident[0])
                    k = ident[0] & ti.u32((1 << self.id_bits) - 1)
                    if self._inside(O) and k < 64:
                        J = self._member(e, O)
                        below = self.entered[J] & ((ti.u64(1) << ti.cast(k, ti.u64)) - ti.u64(1))
                        if ti.cast(ti.math.popcnt(below), ti.i32) < self.cap[J]:
                            if last:
                                D = ti.Vector.zero(ti.i32, self.dim + 1)
                                D[0] = e
                                for a in ti.static(range(self.dim)):
                                    D[a + 1] = cell_of(pool.x[cur, e, p][a], self.real(self.grid.dx[a]), self.n[a])
                                self.count[D] += 1
                        else:
                            pool.keep[e, p] = ti.u8(0)
        for i in range(n_ring):
            J, inside = self._ring_cell(i)
            if inside:
                self.entered[J] = ti.u64(0)

    @ti.func
    def _reflux(self, J):
        """Synchronise ghost cell ``J`` (S1 was done by :meth:`_s1`): S2 of eq. (12), ``q += ΔN / V_c``."""
        vol = ti.static(self.grid.cell_volume)
        self.spde.q[J] += self.real(ti.cast(self.dN[J], ti.f64) / vol)
        self.dN[J] = 0

    @ti.kernel
    def _regrid_apply(self, pool: ti.template(), cur: ti.i32, step: ti.i32, tilt_on: ti.i32):
        """Move to the region in ``fresh``: keep particles still covered, sample newly covered cells."""
        vol = ti.static(self.grid.cell_volume)
        self.need[None] = 0
        self.created[None] = 0
        self.removed[None] = 0.0
        for J in ti.grouped(self.covered):
            if self.fresh[J] and not self.covered[J]:
                C = ti.Vector([J[a + 1] for a in ti.static(range(self.dim))])
                lam = ti.cast(self.spde.q[J], ti.f64) * vol
                m = self._sample(pool, cur, J[0], C, lam, step, step | REGRID_BIRTH, tilt_on)
                self.created[None] += m
                self.removed[None] += lam
                self.count[J] = m  # q is set below: the tilts of other cells read it here
        for J in ti.grouped(self.covered):
            if self.fresh[J] and not self.covered[J]:
                self.spde.q[J] = self.real(ti.cast(self.count[J], ti.f64) / vol)
                self.count[J] = 0
            self.covered[J] = self.fresh[J]
        for e, p in ti.ndrange(self.ensemble, pool.capacity):  # keep what the new region covers
            if p < pool.n[cur, e]:
                D = ti.Vector.zero(ti.i32, self.dim + 1)
                D[0] = e
                for a in ti.static(range(self.dim)):
                    D[a + 1] = cell_of(pool.x[cur, e, p][a], self.real(self.grid.dx[a]), self.n[a])
                pool.keep[e, p] = self.covered[D]
