"""Particles the hybrid samples from the SPDE (paper §3): the ghost ring of every particle
(sub-)step, and the cells a regrid newly covers."""

import math

import taichi as ti

from ..core import rng
from ..core.grid import DIRICHLET, PERIODIC, across, cell_of
from ..methods.particles import Walker
from .region import Region

ID_BITS_MIN = 8  # hybrid particle ids: birth cell in the high bits, at least this many for the index in the cell
# hybrid: particle steps a run may take. A particle's birth word (birth step + 1, or'd with this
# flag for particles sampled at a regrid: REGRID_BIRTH) is shifted left by rng.PURPOSE_BITS
# into one 32-bit counter word (particles.Walker.bits), so birth steps live in 27 bits
HYBRID_STEP_LIMIT = 1 << (32 - rng.PURPOSE_BITS - 1)
REGRID_BIRTH = HYBRID_STEP_LIMIT  # flag in the birth word of particles sampled at a regrid (ghosts: step + 1)
TOO_MANY = 2**31 - 1  # `need` when a cell asked for more particles than an id can number


def _reach(sigma: float) -> tuple[float, float, float]:
    """``(σ, E[w], E[w²])`` of ``w = min(σZ, 1)⁺`` (Z standard normal; σ = √Δt/Δx): the distance in
    cells a clamped step carries a particle towards a face, 0 if it moves away. A particle a
    distance ``v`` (in cells) from the face crosses it iff ``w > v``."""
    a = 1.0 / sigma
    phi0, phia = 1.0 / math.sqrt(2 * math.pi), math.exp(-0.5 * a * a) / math.sqrt(2 * math.pi)
    tail = 0.5 * math.erfc(a / math.sqrt(2))  # P(Z > 1/σ): the clamped steps
    return sigma, sigma * (phi0 - phia) + tail, sigma**2 * (0.5 - tail - a * phia) + tail


def _offset(i: int, a: int) -> int:
    """Component ``a`` of the ``i``-th neighbour offset ``δ ∈ {−1, 0, 1}^d`` (base-3 digits of ``i``)."""
    return (i // 3**a) % 3 - 1


@ti.data_oriented
class Sampler:
    r"""Sampling of particles from a density, keyed on the cell so that the result does not depend
    on the thread order or the box layout.

    Cell ``C`` (padded index ``C + 1``, flattened to ``lin``) gets ``ℓ`` particles plus one with
    probability ``α``, ``ℓ + α = max(λ, 0)`` (paper §3), λ its expected content; particle ``k``
    gets the identity ``id0 = lin · 2^id_bits + k`` and a birth word (``step + 1`` for ghosts,
    ``step | REGRID_BIRTH`` at a regrid), and is placed by :meth:`Walker.in_cell` with the
    linear profile of :meth:`tilt`.
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
        # ghosts drawn as the ones that cross the lead face (:meth:`entering`); not with a potential,
        # whose drift depends on the position
        self.direct = not walker.drifting
        self.reach = [_reach(math.sqrt(walker.dt) / h) for h in self.grid.dx]  # (σ, E w, E w²) per axis
        self.need = ti.field(ti.i32, shape=())  # most slots a member asked for (TOO_MANY: a cell overflowed)
        self.clamped = ti.field(ti.i64, shape=())  # axis steps clamped in the ghosts' walk of the last fill
        self.created = ti.field(ti.i64, shape=())  # particles sampled at the last regrid

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

        With an external potential the profile is exponential (:meth:`Walker.in_cell`), its rate
        the centred slope of ``ln p``, ``β_a = (ln p_{C−e_a} − ln p_{C+e_a}) / 2`` clipped to
        [−50, 50]: at equilibrium ``p ∝ e^{−Ū}`` and β is the potential's rise across the cell, so
        the ghosts lie as e^{−U} does within the cell (exactly, for U linear there).
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
                    b[a] = ti.math.clamp(self.real(0.5) * (lo - hi), self.real(-50.0), self.real(50.0))
                elif qc > 0:
                    b[a] = ti.math.clamp((q[1] - q[0]) / (self.real(2.0) * qc), self.real(-2.0), self.real(2.0))
        return b

    @ti.func
    def _placed(self, e, C, lin, k, step, birth, tilt, lead, walked: ti.template()):
        """Particle ``k`` of cell ``C`` (``lin``: its padded flat index): its identity word, its
        position, whether it is kept and how many of its axis steps were clamped.

        With ``walked`` (a ghost) the position is the one after its walk of sub-step ``step``
        (:meth:`Walker.axis_step` per axis, the steps of :meth:`Walker.move`) and it is kept only
        if it ends in the region; clamped steps are counted for the kept ghosts only. ``lead``
        (:meth:`lead`) names a face that every covered neighbour lies beyond: a step that does
        not cross it cannot end covered, so that axis is stepped first and a ghost that stays on
        this side is dropped without the other axes' normals, moves and the region lookup
        (most are: about one ghost in ten enters). The kept ones are exactly those of
        :meth:`Walker.move`'s step, with its numbers.
        """
        key = ti.math.uvec2(self.key[0], self.key[1])
        id0 = (lin << ti.u32(self.id_bits)) | ti.u32(k)
        r = rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
        y = self.walker.in_cell(C, r, tilt)
        keep, clamped = True, 0
        if ti.static(walked):
            w = self.walker
            drift = ti.Vector.zero(self.real, self.dim)
            if ti.static(w.drifting):
                drift = w.drift(y)
            words = w.own(w.bits(e, id0, ti.u32(birth), ti.u32(step)), id0)
            z, alive, hit = y, True, True
            for a in ti.static(range(self.dim)):
                if lead >> 1 == a:
                    za, ok, c, raw = w.axis_step(y[a], a, words[a], drift[a])
                    z[a], alive, clamped = za, ok, c
                    # 1e-6 of a cell of margin: "crossed" may be said too often, never too rarely
                    lo = self.real((C[a] + 1e-6) * self.grid.dx[a])
                    hi = self.real((C[a] + 1 - 1e-6) * self.grid.dx[a])
                    hit = (lead & 1 == 0 and raw < lo) or (lead & 1 == 1 and raw >= hi)
            keep = False
            if hit:
                for a in ti.static(range(self.dim)):
                    if lead >> 1 != a:
                        za, ok, c, _raw = w.axis_step(y[a], a, words[a], drift[a])
                        z[a], alive, clamped = za, alive and ok, clamped + c
                D = self.region.member(e, ti.Vector([cell_of(z[a], self.real(self.grid.dx[a]), self.n[a])
                                                      for a in ti.static(range(self.dim))]))
                keep = alive and self.region.covered[D] != 0
            y = z
            if not keep:
                clamped = 0
        return id0, y, keep, clamped

    @ti.func
    def lead(self, e, C):
        """``2a + s`` for the first axis ``a`` such that every covered cell ``C + δ`` (``δ ∈ {−1, 0,
        1}^d``, ``δ ≠ 0``, across periodic sides) has ``δ_a = −1`` (``s = 0``) or every one ``+1``
        (``s = 1``): a walk step (at most one cell per axis) from ``C`` that ends covered crosses
        that face. −1 where no axis is such (a ring cell in a concave corner of the region)."""
        total = 0
        lo = ti.Vector.zero(ti.i32, self.dim)
        hi = ti.Vector.zero(ti.i32, self.dim)
        for i in ti.static(range(3**self.dim)):
            if ti.static(i != (3**self.dim - 1) // 2):  # δ = 0: the cell itself
                D = ti.Vector.zero(ti.i32, self.dim)
                ok = True
                for a in ti.static(range(self.dim)):
                    D[a] = C[a] + ti.static(_offset(i, a))
                    if ti.static(self.grid.boundary[a][0] == PERIODIC):
                        D[a] = (D[a] + self.n[a]) % self.n[a]
                    ok = ok and 0 <= D[a] < self.n[a]
                if ok:
                    if self.region.covered[self.region.member(e, D)] != 0:
                        total += 1
                        for a in ti.static(range(self.dim)):
                            if ti.static(_offset(i, a) < 0):
                                lo[a] += 1
                            if ti.static(_offset(i, a) > 0):
                                hi[a] += 1
        out = -1
        for b in ti.static(range(self.dim)):
            a = ti.static(self.dim - 1 - b)  # the last assignment wins: the first axis
            if total > 0 and lo[a] == total:
                out = 2 * a
            elif total > 0 and hi[a] == total:
                out = 2 * a + 1
        return out

    @ti.func
    def _lead_profile(self, lead, tilt):
        """For the lead face ``lead`` (:meth:`lead`) and the cell's profile ``tilt`` (:meth:`tilt`):
        ``(σ, E w, E w², c0, c1)``, the axis's :func:`_reach` and the profile's density at distance
        ``v`` (cells) from the face, ``c0 + c1 v`` (:meth:`Walker.in_cell`: ``1 + b (u − ½)``)."""
        sig, ew, ew2, b = 0.0, 0.0, 0.0, 0.0
        for a in ti.static(range(self.dim)):
            if lead >> 1 == a:
                # (a plain assignment: `sig, ... = ti.static(...)` would bind new names, not assign these)
                sig, ew, ew2 = [ti.f64(ti.static(self.reach[a][i])) for i in ti.static(range(3))]
                b = ti.cast(tilt[a], ti.f64)
        c0, c1 = 1.0 - 0.5 * b, b  # the low face: v = u
        if lead & 1:  # the high face: v = 1 − u
            c0, c1 = 1.0 + 0.5 * b, -b
        return sig, ew, ew2, c0, c1

    @ti.func
    def crossing(self, m, lead, tilt, word):
        r"""How many of the cell's ``m`` ghosts cross its lead face in their walk: ``Bin(m, p)`` (each
        crosses on its own), ``p = ∫∫ (c0 + c1 v) φ(z) 1[w(z) > v] dv dz = c0 E w + c1 E w² / 2``
        (:meth:`_lead_profile`), drawn by inversion of one uniform ``word``."""
        _sig, ew, ew2, c0, c1 = self._lead_profile(lead, tilt)
        p = ti.min(ti.max(c0 * ew + 0.5 * c1 * ew2, 0.0), 1.0 - 1e-12)
        u = rng.uniform(word, ti.f64)
        P = ti.pow(1.0 - p, ti.cast(m, ti.f64))
        F, k = P, 0
        while u > F and k < m:
            P *= ti.cast(m - k, ti.f64) / ti.cast(k + 1, ti.f64) * p / (1.0 - p)
            k += 1
            F += P
        return k

    @ti.func
    def entering(self, e, C, lin, k, step, birth, tilt, lead):
        r"""Ghost ``k`` of the :meth:`crossing` ones of cell ``C``: its identity, its position after its
        walk, whether that is covered and its clamped steps (as :meth:`_placed` with ``walked``).

        Along the lead axis the pair (distance ``v`` to the face, step ``w``) is drawn from its law
        given a crossing, ``∝ (c0 + c1 v) φ(z) 1[v < w(z)]``: ``z`` from the Rayleigh density
        ``z φ(z)`` (``√(−2 ln U)``) kept with probability ``min(1, 1/(σz)) (c0 + c1 w/2) / (c0 +
        max(c1, 0)/2)`` (the clamp, and the profile's mass below ``w``), then ``v`` from ``c0 + c1 v``
        on ``(0, w)`` by inversion; counters ``(id, step, member, SAMPLE_ENTRY + attempt)``. The
        other axes are those of a ghost of :meth:`_placed` (position words, then the walk's), drawn
        without condition: a crossing ends covered or not by them (every covered neighbour lies
        beyond the lead face)."""
        key = ti.math.uvec2(self.key[0], self.key[1])
        id0 = (lin << ti.u32(self.id_bits)) | ti.u32(k)
        sig, _ew, _ew2, c0, c1 = self._lead_profile(lead, tilt)
        top = c0 + 0.5 * ti.max(c1, 0.0)
        w, v, t, done = 0.0, 0.0, 0, False
        while not done and t < 1000:
            r = rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e),
                                             ti.u32(rng.SAMPLE_ENTRY) | (ti.u32(t) << rng.PURPOSE_BITS)), key)
            z = ti.sqrt(-2.0 * ti.log(rng.uniform(r[0], ti.f64)))
            w = ti.min(sig * z, 1.0)
            done = rng.uniform(r[1], ti.f64) * top * ti.max(sig * z, 1.0) < c0 + 0.5 * c1 * w
            R = rng.uniform(r[2], ti.f64) * (c0 * w + 0.5 * c1 * w * w)
            v = 2.0 * R / (c0 + ti.sqrt(ti.max(c0 * c0 + 2.0 * c1 * R, 0.0)))
            t += 1
        y = ti.Vector.zero(self.real, self.dim)
        words = ti.math.uvec4(0)
        if ti.static(self.dim > 1):
            p = rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_POSITION)), key)
            y = self.walker.in_cell(C, p, tilt)
            words = self.walker.own(self.walker.bits(e, id0, ti.u32(birth), ti.u32(step)), id0)
        alive, clamped = True, 0
        for a in ti.static(range(self.dim)):
            h, L = ti.static(self.grid.dx[a], self.grid.lengths[a])
            if lead >> 1 == a:
                x = (ti.cast(C[a], ti.f64) + v - w) * h  # the low face: from v above it to w − v below
                if lead & 1:
                    x = (ti.cast(C[a], ti.f64) + 1.0 - v + w) * h
                if ti.static(self.grid.boundary[a][0] == PERIODIC):
                    if x < 0:
                        x += L
                    elif x >= L:
                        x -= L
                y[a] = self.real(x)
                clamped = ti.cast(w >= 1.0, ti.i32)
            else:
                ya, ok, c, _raw = self.walker.axis_step(y[a], a, words[a], self.real(0.0))
                y[a], alive, clamped = ya, alive and ok, clamped + c
        D = self.region.member(e, ti.Vector([cell_of(y[a], self.real(self.grid.dx[a]), self.n[a])
                                              for a in ti.static(range(self.dim))]))
        keep = alive and self.region.covered[D] != 0
        if not keep:
            clamped = 0
        return id0, y, keep, clamped

    @ti.func
    def _ghost(self, e, C, lin, k, step, birth, tilt, lead):
        """Ghost ``k`` of :meth:`sample`: :meth:`entering` where the cell has a lead face and no
        potential drifts, else :meth:`_placed` with the walk."""
        id0, y, keep, cl = ti.u32(0), ti.Vector.zero(self.real, self.dim), False, 0
        if ti.static(self.direct):
            if lead >= 0:
                id0, y, keep, cl = self.entering(e, C, lin, k, step, birth, tilt, lead)
            else:
                id0, y, keep, cl = self._placed(e, C, lin, k, step, birth, tilt, lead, 1)
        else:
            id0, y, keep, cl = self._placed(e, C, lin, k, step, birth, tilt, lead, 1)
        return id0, y, keep, cl

    @ti.func
    def sample(self, pool: ti.template(), buf, e, C, lam, step, birth, tilt_on, walked: ti.template()):
        """Sample ℓ particles plus one with probability α (``lam = ℓ + α``) in cell ``C`` (paper §3),
        placed by :meth:`tilt` (uniform where ``tilt_on`` is 0), and append them to buffer ``buf``
        of member ``e`` (the pool's unit for that cell: :mod:`pool`); returns how many were sampled.

        With ``walked`` (the ghosts of a particle sub-step ``step``) only the ghosts whose walk ends
        in the region are appended, in index order, already walked (the hybrid's walk does not
        move them again): where the cell has a lead face and no potential, the :meth:`crossing`
        ones drawn by :meth:`entering`, else each ghost walked by :meth:`_placed`. Those that enter
        are found in a first pass, remembered by index (below 64) and placed again in the second.
        ``walked`` is a compile-time flag: the regrid's ``cover`` does not compile the walk."""
        lin = ti.u32(0)
        for a in ti.static(range(self.dim)):
            lin = lin * ti.u32(self.region.padded[a]) + ti.u32(C[a] + 1)
        key = ti.math.uvec2(self.key[0], self.key[1])
        bits = rng.philox4x32(ti.math.uvec4(lin, ti.u32(step), self.walker.member(e), ti.u32(rng.SAMPLE_COUNT)), key)
        m = self.walker.how_many(ti.max(lam, 0.0), bits[0])
        if m >= (1 << self.id_bits):
            ti.atomic_max(self.need[None], TOO_MANY)
            m = 0
        tilt = ti.Vector.zero(self.real, self.dim)
        if m > 0 and tilt_on and self.region.inside(C):
            tilt = self.tilt(e, C)
        c, low, clamped = m, ti.u64(0), 0  # appended; which of ghosts 0–63 enter; clamped axes
        lead, n = -1, m  # the cell's lead face; the ghosts to walk: all, or those that cross it
        if ti.static(walked):
            c = 0
            if m > 0:
                lead = self.lead(e, C)
            if ti.static(self.direct):
                if lead >= 0:
                    n = self.crossing(m, lead, tilt, bits[1])
            for k in range(n):
                _id, _y, keep, cl = self._ghost(e, C, lin, k, step, birth, tilt, lead)
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
        for k in range(n):
            if ti.static(not walked) or k >= 64 or (low >> ti.cast(k, ti.u64)) & ti.u64(1):
                id0, y, keep = ti.u32(0), ti.Vector.zero(self.real, self.dim), True
                if ti.static(walked):
                    id0, y, keep, _ = self._ghost(e, C, lin, k, step, birth, tilt, lead)
                else:
                    id0, y, keep, _ = self._placed(e, C, lin, k, step, birth, tilt, lead, 0)
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
