"""Particles the hybrid samples from the SPDE (paper §3): the ghost ring of every particle
(sub-)step, and the cells a regrid newly covers."""

import math

import numpy as np
import taichi as ti

from ..core import rng
from ..core.grid import DIRICHLET, across, cell_of
from ..methods.particles import Walker
from .region import Region

ID_BITS_MIN = 8  # hybrid particle ids: birth cell in the high bits, at least this many for the index in the cell
# hybrid: particle steps a run may take. A particle's birth word (birth step + 1, or'd with this
# flag for particles sampled at a regrid: REGRID_BIRTH) is shifted left by rng.PURPOSE_BITS
# into one 32-bit counter word (particles.Walker.bits), so birth steps live in 27 bits
HYBRID_STEP_LIMIT = 1 << (32 - rng.PURPOSE_BITS - 1)
REGRID_BIRTH = HYBRID_STEP_LIMIT  # flag in the birth word of particles sampled at a regrid (ghosts: step + 1)
TOO_MANY = 2**31 - 1  # `need` when a cell asked for more particles than an id can number
PROFILE_PIECES = 4  # with a potential: pieces per cell and axis of the in-cell Boltzmann profile (Sampler.place)


@ti.data_oriented
class Sampler:
    r"""Sampling of particles from a density, keyed on the cell so that the result does not depend
    on the thread order or the box layout.

    Cell ``C`` (padded index ``C + 1``, flattened to ``lin``) gets ``ℓ`` particles plus one with
    probability ``α``, ``ℓ + α = max(λ, 0)`` (paper §3), λ its expected content; particle ``k``
    gets the identity ``id0 = lin · 2^id_bits + k`` and a birth word (``step + 1`` for ghosts,
    ``step | REGRID_BIRTH`` at a regrid), and is placed by :meth:`place` with the profile of
    :meth:`tilt` (with a potential along e^{−U} within the cell: :attr:`nodes`, ``dim ×
    (PROFILE_PIECES + 1)`` numbers a cell, made once).
    """

    def __init__(self, spde, region: Region, walker: Walker, profile: str, substeps: int):
        self.spde, self.region, self.walker, self.profile, self.substeps = spde, region, walker, profile, substeps
        self.grid, self.dim, self.n, self.real = spde.grid, spde.dim, spde.n, spde.real
        self.key = spde.key  # the run's Philox key; sampling has counters of its own (rng.SAMPLE_*)
        self.id_bits = 32 - math.ceil(math.log2(math.prod(region.padded)))  # bits for the index in the cell
        assert self.id_bits >= ID_BITS_MIN, "scene.load.make_scene refuses such grids"
        assert profile != "mean" or spde.track_mean, "ghost_profile 'mean' reads the SPDE's q̄"
        if substeps > 1:
            self.q_old = ti.field(spde.real, shape=(spde.ensemble, *self.n))  # q^n while q holds q^{n+1,*} [1/volume]
        self.need = ti.field(ti.i32, shape=())  # most slots a member asked for (TOO_MANY: a cell overflowed)
        self.clamped = ti.field(ti.i64, shape=())  # axis steps clamped in the ghosts' walk of the last fill
        self.created = ti.field(ti.i64, shape=())  # particles sampled at the last regrid
        self.shaped = walker.drifting and profile != "uniform"  # placed along e^{-U} within the cell (place)
        if self.shaped:
            # per cell and axis: −ln of e^{−U}'s marginal at the PROFILE_PIECES + 1 points from the lower
            # face to the upper one, less the cell's Ū [k_BT] (Potential.axis_profiles)
            self.nodes = ti.Matrix.field(self.dim, PROFILE_PIECES + 1, spde.real, shape=self.n)
            nodes = spde.grid.potential.axis_profiles(self.n, spde.grid.lengths, PROFILE_PIECES)
            nodes = np.clip(np.nan_to_num(nodes, nan=0.0, posinf=500.0, neginf=-500.0), -500.0, 500.0)  # (e^{−500}: none)
            self.nodes.from_numpy(nodes.astype(np.float32 if spde.real == ti.f32 else np.float64))

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
    def _profile(self, J):
        """The density the tilts are read from at member-first index ``J``: q̄ (``mean``) or q."""
        v = self.real(0.0)
        if ti.static(self.profile == "mean"):
            J0 = J
            J0[0] = 0
            v = self.spde.qbar[J0]
        else:
            v = self.spde.q[J]
        return v

    @ti.func
    def tilt(self, e, C):
        r"""Linear profile of cell ``C`` for :meth:`Walker.in_cell`: ``b_a = (p_{C+e_a} − p_{C−e_a}) / (2 p_C)``
        clipped to [−2, 2] so the density stays ≥ 0: the centred slope of the profile density ``p``
        (the neighbours :func:`grid.across` each face: a Neumann side mirrors, a Dirichlet side
        sees its reservoir). Zero with ``ghost_profile = 'uniform'``.

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

        With an external potential the tilt is that of the Slotboom variable ``g = p e^{Ū}`` (the
        density the Scharfetter–Gummel flux differences, :func:`~ti_dk.methods.fluxes.drift_coefficients`),
        exponential: ``γ_a = (ln g_{C−e_a} − ln g_{C+e_a}) / 2`` clipped to [−50, 50], read as
        ``ln p`` less the Ū differences across both faces (``c_R − c_L`` of the faces' weights);
        :meth:`place` lays it over e^{−U} within the cell. At equilibrium ``g`` is flat, γ = 0,
        and the particles lie as e^{−U} does in the cell; with a current through it, ``g`` carries
        the current's slope. (An exponential profile with the centred slope of ``ln p`` alone
        ignores U's curvature within the cell: where U changes by more than ≈ 1 k_BT a cell it
        misjudges the density at the faces, by ≈ (ln p)''Δx²/12, and with it the ghosts' inflow;
        benchmarks/RESULTS.md, the double well's crossing rate.)
        """
        b = ti.Vector.zero(self.real, self.dim)
        if ti.static(self.profile != "uniform"):
            J = self.region.member(e, C)
            qc = self._profile(J)
            for a in ti.static(range(self.dim)):
                q = ti.Vector([qc, qc])  # beyond a Neumann side: the mirror image
                for side in ti.static(range(2)):
                    K, inside = across(self.grid, J, a, side)
                    if inside:
                        q[side] = self._profile(K)
                    elif ti.static(self.grid.boundary[a][side] == DIRICHLET):
                        q[side] = self.real(self.grid.reservoir[a][side])
                if ti.static(self.walker.drifting):
                    tiny = ti.static(1e-300 if self.real == ti.f64 else 1e-30)
                    lo, hi = ti.log(ti.max(q[0], self.real(tiny))), ti.log(ti.max(q[1], self.real(tiny)))
                    J0 = J
                    J0[0] = 0
                    c_lo, c_hi = self.spde.coef[J0], self.spde.coef[self.spde.upper(J0, a)]
                    rise = c_lo[2 * a + 1] - c_lo[2 * a] + c_hi[2 * a + 1] - c_hi[2 * a]  # Ū_{C+e_a} − Ū_{C−e_a}
                    b[a] = ti.math.clamp(self.real(0.5) * (lo - hi - rise), self.real(-50.0), self.real(50.0))
                elif qc > 0:
                    b[a] = ti.math.clamp((q[1] - q[0]) / (self.real(2.0) * qc), self.real(-2.0), self.real(2.0))
        return b

    @ti.func
    def place(self, C, bits, tilt, shaped):
        r"""A position in cell ``C`` from the words ``bits`` (one per axis): :meth:`Walker.in_cell`'s
        linear profile with ``tilt``, or with a potential and ``shaped`` (a grid cell whose tilt
        was read) along each axis the density ``∝ exp(−V_a(u) − γ_a u)``, ``γ = tilt``, ``V_a``
        the piecewise-linear interpolation of :attr:`nodes` (:data:`PROFILE_PIECES` pieces), drawn
        by inverting its CDF: the piece by its share of the mass, then the truncated exponential
        within it (one uniform per axis)."""
        y = ti.Vector.zero(self.real, self.dim)
        if ti.static(self.shaped):
            if shaped:
                P = ti.static(PROFILE_PIECES)
                V = self.nodes[C]
                for a in ti.static(range(self.dim)):
                    E = ti.Vector([V[a, k] + tilt[a] * self.real(k / P) for k in ti.static(range(P + 1))])
                    w = ti.exp(E.min() - E)  # e^{−E} at the points, the largest 1
                    m = ti.Vector.zero(self.real, P)  # each piece's mass (times P)
                    for k in ti.static(range(P)):
                        d = E[k + 1] - E[k]
                        m[k] = ti.select(ti.abs(d) < 1e-6, w[k], (w[k] - w[k + 1]) / ti.select(d == 0, self.real(1.0), d))
                    r = rng.uniform(bits[a], self.real) * m.sum()
                    piece, below, cum, mass, d = 0, self.real(0.0), self.real(0.0), m[0], E[1] - E[0]
                    for k in ti.static(range(1, P)):  # the piece in which the cumulative mass passes r
                        cum += m[k - 1]
                        if r >= cum:
                            piece, below, mass, d = k, cum, m[k], E[k + 1] - E[k]
                    s = ti.math.clamp((r - below) / mass, self.real(0.0), self.real(1.0))
                    t = s - self.real(0.5) * d * s * (self.real(1.0) - s)
                    if ti.abs(d) > 1e-4:
                        t = -ti.log(self.real(1.0) - s * (self.real(1.0) - ti.exp(-d))) / d
                    u = ti.min((piece + t) / P, self.real(1.0 - 2.0**-24))  # inside the cell whatever the rounding
                    y[a] = (self.real(C[a]) + u) * self.real(self.grid.dx[a])
            else:
                y = self.walker.in_cell(C, bits, tilt)
        else:
            y = self.walker.in_cell(C, bits, tilt)
        return y

    @ti.func
    def _placed(self, e, C, lin, k, step, birth, tilt, shaped, walked: ti.template()):
        """Particle ``k`` of cell ``C`` (``lin``: its padded flat index): its identity word, its
        position, whether it is kept and how many of its axis steps were clamped. With ``walked``
        the position is the one after its walk of sub-step ``step`` (:meth:`Walker.move`, the
        same numbers the hybrid's walk would draw) and it is kept only if it ends in the region."""
        key = ti.math.uvec2(self.key[0], self.key[1])
        id0 = (lin << ti.u32(self.id_bits)) | ti.u32(k)
        r = rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
        y = self.place(C, r, tilt, shaped)
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
        placed by :meth:`tilt` (uniform where ``tilt_on`` is 0), and append them to buffer ``buf``
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
            tilt, shaped = self.tilt(e, C), True
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
