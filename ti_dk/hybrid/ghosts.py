"""Particles the hybrid samples from the SPDE (paper §3): the ghost ring of every particle
(sub-)step, and the cells a regrid newly covers."""

import math

import taichi as ti

from ..core import rng
from ..core.grid import cell_of
from ..methods.particles import Walker
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
        self.need = ti.field(ti.i32, shape=())  # most slots a member asked for (TOO_MANY: a cell overflowed)
        self.clamped = ti.field(ti.i64, shape=())  # axis steps clamped in the ghosts' walk of the last fill
        self.created = ti.field(ti.i64, shape=())  # particles sampled at the last regrid
        self.incell = InCell(spde, region, walker, profile)  # where in its cell a sampled particle lies

    def check_need(self) -> int:
        """The most slots a member asked for in the last fill; raises if a cell overflowed its ids."""
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
    def _placed(self, e, C, lin, k, step, birth, tilt, shaped, walked: ti.template()):
        """Particle ``k`` of cell ``C`` (``lin``: its padded flat index): its identity word, its
        position, whether it is kept and how many of its axis steps were clamped. With ``walked``
        the position is the one after its walk of sub-step ``step`` (:meth:`Walker.move`, the
        same numbers the hybrid's walk would draw) and it is kept only if it ends in the region."""
        key = ti.math.uvec2(self.key[0], self.key[1])
        id0 = (lin << ti.u32(self.id_bits)) | ti.u32(k)
        r = rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
        y = self.incell.place(C, r, tilt, shaped)
        keep, clamped = True, 0
        if ti.static(walked):
            z, alive, c = self.walker.move(y, e, id0, ti.u32(birth), ti.u32(step))
            D = self.region.member(e, ti.Vector([cell_of(z[a], self.real(self.grid.dx[a]), self.n[a])
                                                  for a in ti.static(range(self.dim))]))
            keep = alive and self.region.covered[D] != 0
            y, clamped = z, c
        return id0, y, keep, clamped

    @ti.func
    def sample(self, pool: ti.template(), buf, e, C, lam, step, birth, tilt_on, walked: ti.template()):
        """Sample ℓ particles plus one with probability α (``lam = ℓ + α``) in cell ``C`` (paper §3),
        placed by :meth:`InCell.tilt` (uniform where ``tilt_on`` is 0), and append them to buffer ``buf``
        of member ``e`` (the pool's unit for that cell: :mod:`pool`); returns how many were sampled.

        With ``walked`` (the ghosts of a particle sub-step ``step``) each is walked at once
        (:meth:`_placed`) and only those that end in the region are appended, in index order: a
        ghost that stays out takes no slot, and the hybrid's walk does not move it again. Most
        ghosts stay out (ellipse2d: of 17,000 ghosts a step about 1,600 enter; the walk went
        from 63,400 particles a step to 48,000).
        The ghosts that enter are found in a first pass, remembered by index (below 64) and
        placed again in the second; a cell of more ghosts places those beyond 63 twice.
        ``walked`` is a compile-time flag: the regrid's ``cover`` does not compile the walk
        (sphere3d at 64³: that kernel's first call, from the offline cache, 1.5–1.6 → 0.8–1.0 s)."""
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
        c, low, clamped = m, ti.u64(0), 0  # appended; which of ghosts 0–63 enter; clamped axes
        if ti.static(walked):
            c = 0
            for k in range(m):
                _id, _y, keep, cl = self._placed(e, C, lin, k, step, birth, tilt, shaped, walked)
                clamped += cl
                if keep:
                    c += 1
                    if k < 64:
                        low |= ti.u64(1) << ti.cast(k, ti.u64)
            if clamped:
                self.clamped[None] += clamped
        U = pool.unit_of(e, C)
        base = pool.append(buf, U, c)
        ti.atomic_max(self.need[None], base + c)
        j = base
        for k in range(m):
            if ti.static(not walked) or k >= 64 or (low >> ti.cast(k, ti.u64)) & ti.u64(1):
                id0, y, keep, _ = self._placed(e, C, lin, k, step, birth, tilt, shaped, walked)
                if keep:
                    if j < pool.capacity:
                        I = pool.index(buf, U, j)
                        pool.x[I] = y
                        pool.pid[I] = ti.math.uvec2(id0, ti.u32(birth))
                    j += 1
        return m

    # -- kernels --------------------------------------------------------------------------
    @ti.kernel
    def fill(self, pool: ti.template(), cur: ti.i32, step: ti.i32, n_ring: ti.i32, w: ti.f64, tilt_on: ti.i32,
             walked: ti.template()):
        """Step 1 of the hybrid: ghost particles appended after the real ones, from
        ``(1 − w) q^n + w q^{n+1,*}`` (``w = s/k`` at particle sub-step s of k; q^n itself when
        k = 1) or the Dirichlet reservoir; with ``walked`` already walked, only those that enter
        the region (:meth:`sample`)."""
        vol = ti.static(self.grid.cell_volume)
        self.need[None] = 0
        self.clamped[None] = 0
        for i in range(n_ring):
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
            self.sample(pool, cur, J[0], C, lam, step, step + 1, tilt_on, walked)

    @ti.kernel
    def cover(self, pool: ti.template(), cur: ti.i32, step: ti.i32, tilt_on: ti.i32, scratch: ti.template(),
              cells: ti.types.ndarray(dtype=ti.i32, ndim=1), n_new: ti.i32, n_gone: ti.i32, mark: ti.i32):
        """Move the region by the cells :meth:`Region.stage` listed in ``cells`` (flat indices: the
        ``n_new`` it gains, then the ``n_gone`` it loses): sample the newly covered cells (birth
        ``step | REGRID_BIRTH``), whose q becomes N / V_c, and with ``mark`` mark to keep the
        particles still covered (a region that only grows keeps them all: the caller then skips
        the marks, a pass over every particle). Loops over the listed cells, not the grid (the
        work follows the region, as an extension's should). ``scratch`` (i32 per cell, zero) holds the
        counts until every tilt has read q."""
        vol = ti.static(self.grid.cell_volume)
        covered, shape = ti.static(self.region.covered, self.region.covered.shape)
        self.need[None] = 0
        self.created[None] = 0
        for i in range(n_new):
            J = self.region.unflatten(cells[i], shape)
            C = ti.Vector([J[a + 1] for a in ti.static(range(self.dim))])
            lam = ti.cast(self.spde.q[J], ti.f64) * vol
            m = self.sample(pool, cur, J[0], C, lam, step, step | REGRID_BIRTH, tilt_on, 0)
            self.created[None] += m
            scratch[J] = m
        for i in range(n_new + n_gone):
            J = self.region.unflatten(cells[i], shape)
            if i < n_new:
                self.spde.q[J] = self.real(ti.cast(scratch[J], ti.f64) / vol)
                scratch[J] = 0
                covered[J] = ti.u8(1)
            else:
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
