"""Particles the hybrid samples from the SPDE (paper §3): the ghost ring of every particle
(sub-)step, and the cells a regrid newly covers."""

import math

import taichi as ti

from ..core import rng
from ..core.grid import cell_of, spread
from ..methods.particles import Walker
from .crossings import Crossings
from .incell import InCell
from .region import Region

ID_BITS_MIN = 8  # hybrid particle ids: birth cell in the high bits, at least this many for the index in the cell
# hybrid: particle steps a run may take. A particle's birth word (birth step + 1, or'd with this
# flag for particles sampled at a regrid: REGRID_BIRTH) is shifted left by rng.PURPOSE_BITS
# into one 32-bit counter word (particles.Walker.bits), so birth steps live in 27 bits
HYBRID_STEP_LIMIT = 1 << (32 - rng.PURPOSE_BITS - 1)
REGRID_BIRTH = HYBRID_STEP_LIMIT  # flag in the birth word of particles sampled at a regrid (ghosts: step + 1)
TOO_MANY = 2**31 - 1  # `need` when a cell asked for more particles than an id can number


@ti.data_oriented
class Sampler:
    r"""Sampling of particles from a density, keyed on the cell so that the result does not depend
    on the thread order or the box layout.

    Cell ``C`` (padded index ``C + 1``, flattened to ``lin``) gets ``ℓ`` particles plus one with
    probability ``α``, ``ℓ + α = max(λ, 0)`` (paper §3), λ its expected content; particle ``k``
    gets the identity ``id0 = lin · 2^id_bits + k`` and a birth word (``step + 1`` for ghosts,
    ``step | REGRID_BIRTH`` at a regrid), and is placed by :meth:`InCell.place` with the profile of
    :meth:`InCell.tilt`.
    """

    def __init__(self, spde, region: Region, walker: Walker, profile: str, substeps: int):
        self.spde, self.region, self.walker, self.substeps = spde, region, walker, substeps
        self.grid, self.dim, self.n, self.real = spde.grid, spde.dim, spde.n, spde.real
        self.key = spde.key  # the run's Philox key; sampling has counters of its own (rng.SAMPLE_*)
        self.id_bits = 32 - math.ceil(math.log2(math.prod(region.padded)))  # bits for the index in the cell
        assert self.id_bits >= ID_BITS_MIN, "scene.load.make_scene refuses such grids"
        if substeps > 1:
            self.q_old = ti.field(spde.real, shape=(spde.ensemble, *self.n))  # q^n while q holds q^{n+1,*} [1/volume]
        self.crossings = Crossings(self.grid, region, walker, self.key)  # the ghosts' walk into the region
        self.need = ti.field(ti.i32, shape=())  # most slots a member asked for (TOO_MANY: a cell overflowed)
        self.clamped = ti.field(ti.i64, shape=())  # axis steps clamped in the ghosts' walk of the last fill
        self.created = ti.field(ti.i64, shape=())  # particles sampled at the last regrid
        self.incell = InCell(spde, region, walker, profile)  # where in its cell a sampled particle lies

    def check_need(self, need: int | None = None) -> int:
        """The most slots a member asked for in the last fill or cover (``need``: as :meth:`fill`
        returned it, else read); raises if a cell overflowed its ids."""
        if need is None:
            need = self.need[None]
        if need == TOO_MANY:
            raise OverflowError(
                f"a ghost or newly covered cell holds more than {2**self.id_bits - 1} particles: "
                "lower the density or use fewer cells")
        return int(need)

    # -- identities -----------------------------------------------------------------------
    @ti.func
    def origin(self, id0):
        """The birth cell of a particle (it may be a reservoir cell, one layer outside)."""
        lin = ti.cast(id0 >> ti.u32(self.id_bits), ti.i32)
        C = ti.Vector.zero(ti.i32, self.dim)
        for b in ti.static(range(self.dim)):
            a = ti.static(self.dim - 1 - b)
            C[a] = lin % self.region.padded[a] - 1
            lin //= self.region.padded[a]
        return C

    @ti.func
    def index(self, id0):
        """The index of a particle among those sampled with it in its birth cell."""
        return id0 & ti.u32((1 << self.id_bits) - 1)

    # -- placement ------------------------------------------------------------------------
    @ti.func
    def _placed(self, e, C, lin, k, step, birth, tilt, shaped, lead, walked: ti.template()):
        """Particle ``k`` of cell ``C`` (``lin``: its padded flat index): identity, position, kept,
        clamped steps; placed by :meth:`InCell.place`, and with ``walked`` (a ghost, with a potential)
        walked (:meth:`Crossings.walk`, along its ``lead`` face first) and kept only if its walk ends
        in the region."""
        key = ti.math.uvec2(self.key[0], self.key[1])
        id0 = (lin << ti.u32(self.id_bits)) | ti.u32(k)
        keep, clamped = True, 0
        r = rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
        y = self.incell.place(C, r, tilt, shaped)
        if ti.static(walked):
            y, keep, clamped = self.crossings.walk(e, C, id0, y, step, birth, lead)
        return id0, y, keep, clamped

    @ti.func
    def _store(self, pool: ti.template(), buf, U, j, id0, y, birth):
        """Particle ``id0`` at ``y`` into slot ``j`` of unit ``U``, unless past the capacity (the
        caller counts it in ``need``, grows the pool and samples again)."""
        if j < pool.capacity:
            I = pool.index(buf, U, j)
            pool.x[I] = y
            pool.pid[I] = ti.math.uvec2(id0, ti.u32(birth))

    @ti.func
    def sample(self, pool: ti.template(), buf, e, C, lam, step, birth, tilt_on, near, walked: ti.template()):
        """Sample ℓ particles plus one with probability α (``lam = ℓ + α``) in cell ``C`` (paper §3),
        placed by :meth:`InCell.tilt` (uniform where ``tilt_on`` is 0), and append them to buffer ``buf``
        of member ``e`` (the pool's unit for that cell: :mod:`pool`); returns how many were sampled.

        With ``walked`` (the ghosts of a particle sub-step ``step``) only the ghosts whose walk ends
        in the region are appended, already walked (the hybrid's walk does not move them again):
        without a potential those :meth:`Crossings.count` draws, each by :meth:`Crossings.entrant`
        (one atomic a cell for their slots); with one, each ghost walked by :meth:`_placed` and
        appended where it ends covered. ``near`` is the cell's covered neighbours
        (:attr:`Region.near_list`). (The slots' order is the threads'; a particle's numbers are
        keyed on its identity, and :meth:`pools.occupied` sorts.) ``walked`` is a compile-time
        flag: the regrid's ``cover`` does not compile the walk."""
        lin = ti.u32(0)
        for a in ti.static(range(self.dim)):
            lin = lin * ti.u32(self.region.padded[a]) + ti.u32(C[a] + 1)
        key = ti.math.uvec2(self.key[0], self.key[1])
        bits = rng.philox4x32(ti.math.uvec4(lin, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_COUNT)), key)
        m = self.walker.how_many(ti.max(lam, 0.0), bits[0])
        if m >= (1 << self.id_bits):
            ti.atomic_max(self.need[None], TOO_MANY)
            m = 0
        tilt, shaped = ti.Vector.zero(self.real, self.dim), False
        if m > 0 and tilt_on and self.region.inside(C):
            tilt, shaped = self.incell.tilt(e, C), True
        U = pool.unit_of(e, C)
        if ti.static(walked):
            clamped, top = 0, 0  # clamped steps of the entrants; slots used
            if ti.static(self.crossings.direct):
                n, run = self.crossings.count(m, near, C, tilt, bits[1])
                if n > 0:
                    base = pool.append(buf, U, n)
                    top = base + n
                    for k in range(n):
                        id0 = (lin << ti.u32(self.id_bits)) | ti.u32(k)
                        y, cl = self.crossings.entrant(e, C, id0, step, near, tilt, run)
                        clamped += cl
                        self._store(pool, buf, U, base + k, id0, y, birth)
            else:
                lead = self.crossings.lead(near)
                for k in range(m):
                    id0, y, keep, cl = self._placed(e, C, lin, k, step, birth, tilt, shaped, lead, walked)
                    if keep:
                        clamped += cl
                        j = pool.append(buf, U, 1)
                        top = ti.max(top, j + 1)
                        self._store(pool, buf, U, j, id0, y, birth)
            ti.atomic_max(self.need[None], top)
            if clamped:
                self.clamped[None] += clamped
        else:
            base = pool.append(buf, U, m)
            ti.atomic_max(self.need[None], base + m)
            for k in range(m):
                id0, y, _keep, _cl = self._placed(e, C, lin, k, step, birth, tilt, shaped, -1, walked)
                self._store(pool, buf, U, base + k, id0, y, birth)
        return m

    # -- kernels --------------------------------------------------------------------------
    @ti.kernel
    def fill(self, pool: ti.template(), cur: ti.i32, step: ti.i32, n_ring: ti.i32, w: ti.f64, tilt_on: ti.i32,
             walked: ti.template()) -> ti.i32:
        """Step 1 of the hybrid: ghost particles appended after the real ones, from
        ``(1 − w) q^n + w q^{n+1,*}`` (``w = s/k`` at particle sub-step s of k; q^n itself when
        k = 1) or the Dirichlet reservoir; with ``walked`` already walked, only those that enter
        the region (:meth:`sample`). Returns :attr:`need` (for :meth:`check_need`: a field read
        from Python is a kernel launch of its own)."""
        vol = ti.static(self.grid.cell_volume)
        self.need[None] = 0
        self.clamped[None] = 0
        for i, s in ti.ndrange(n_ring, spread(n_ring)):  # a few hundred ghost cells would run on one thread
            if s != 0:
                continue
            J, inside = self.region.ring_cell(i)
            C = ti.Vector([J[a + 1] for a in ti.static(range(self.dim))])
            lam = 0.0
            if inside:
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
            self.sample(pool, cur, J[0], C, lam, step, step + 1, tilt_on, self.region.near_list[i], walked)
        return self.need[None]

    @ti.kernel
    def cover(self, pool: ti.template(), cur: ti.i32, step: ti.i32, tilt_on: ti.i32, scratch: ti.template(),
              target: ti.template(), mark: ti.i32):
        """Move the region to ``target`` (a cell mask, ``(ensemble, *cells)``: :attr:`Tally.target`):
        sample the cells it covers anew (birth ``step | REGRID_BIRTH``), whose q becomes N / V_c,
        uncover those it leaves, and with ``mark`` mark to keep the particles still covered (a
        region that only grows keeps them all: the caller then skips the marks, a pass over every
        particle). Two passes over the grid, a compare a cell, on the device (no list of the
        changed cells from the host). ``scratch`` (i32 per cell, zero) holds the counts until
        every tilt has read q."""
        vol = ti.static(self.grid.cell_volume)
        covered = ti.static(self.region.covered)
        self.need[None] = 0
        self.created[None] = 0
        for J in ti.grouped(target):
            if target[J] != 0 and covered[J] == 0:
                C = ti.Vector([J[a + 1] for a in ti.static(range(self.dim))])
                lam = ti.cast(self.spde.q[J], ti.f64) * vol
                m = self.sample(pool, cur, J[0], C, lam, step, step | REGRID_BIRTH, tilt_on, ti.u32(0), 0)
                self.created[None] += m
                scratch[J] = m
        for J in ti.grouped(target):
            if target[J] != 0 and covered[J] == 0:
                self.spde.q[J] = self.real(ti.cast(scratch[J], ti.f64) / vol)
                scratch[J] = 0
                covered[J] = ti.u8(1)
            elif target[J] == 0 and covered[J] != 0:
                covered[J] = ti.u8(0)
        for u in range(pool.units(cur) * mark):
            e, U, lo, hi = pool.unit(cur, u)
            for p in range(lo, hi):
                I = pool.index(cur, U, p)
                D = ti.Vector.zero(ti.i32, self.dim + 1)
                D[0] = e
                for a in ti.static(range(self.dim)):
                    D[a + 1] = cell_of(pool.x[I][a], self.real(self.grid.dx[a]), self.n[a])
                pool.mark(I, covered[D] != 0, D)
