"""The face fluxes and the update of the finite-volume Dean–Kawasaki scheme and its Gaussian
version (paper eq. 8–11), as kernels of :class:`~.fv.SPDESolver`, and the drift of an external
potential (Scharfetter–Gummel coefficients, :func:`drift_coefficients`)."""

import numpy as np
import taichi as ti

from ..core import rng
from ..core.grid import DIRICHLET, NEUMANN, PERIODIC, across, face_kind


@ti.data_oriented
class Fluxes:
    r"""The two parts of one finite-volume step on every member, as the loops that
    :class:`~.fv.SPDESolver`'s kernels run: :meth:`fluxes` makes the face fluxes of eq. (8) (the
    noise keyed on seed, member, step and face), :meth:`update` applies eq. (9) (and eq. 10 for
    q̄). The fields they use are made by :class:`~.fv.SPDESolver`."""

    @ti.func
    def _pair(self, f: ti.template(), J, a: ti.template(), reservoir: ti.template()):
        """Values of ``f`` left and right of the lower face of cell ``J`` along axis ``a``.

        ``J`` carries the member index first; the left cell is :func:`grid.across` the face (a
        periodic image), or beyond a side the Dirichlet reservoir value ``reservoir[a]`` (the
        density, or its square root); so is the right one of the upper boundary face ``n_a``.
        """
        res_lo, res_hi = ti.static(reservoir[a])
        L, has_left = across(self.grid, J, a, 0)
        v = ti.Vector([self.real(0.0), self.real(0.0)])
        if not has_left:
            v = ti.Vector([self.real(res_lo), f[J]])
        elif J[a + 1] == ti.static(self.n[a]):
            v = ti.Vector([f[L], self.real(res_hi)])
        else:
            v = ti.Vector([f[L], f[J]])
        return v

    @ti.func
    def _inside_replaced(self, J):
        """Whether the ``G`` cells from ``J`` along the last axis and the cells across their lower
        faces are all :attr:`replaced` (so none of those faces' fluxes is read); a boundary face
        never is. One read decides the common case, a cell not replaced."""
        inside = False
        if ti.static(self.replacing):
            inside = True
            K = J
            for g in ti.static(range(self.group)):
                if inside:
                    if K[self.dim] >= self.n[self.dim - 1] or self.replaced[K] == 0:
                        inside = False
                    else:
                        for a in ti.static(range(self.dim)):
                            L, has_left = across(self.grid, K, a, 0)
                            if not has_left or self.replaced[L] == 0:
                                inside = False
                K[self.dim] += 1
        return inside

    @ti.func
    def _face_noise(self, J, step, key):
        """The four Philox words of the counter group holding cell ``J`` (member index first), under
        ``key`` (:attr:`key`'s two words, which a loop may read once before it: see ``_step_members``).

        Groups are numbered on the padded face grid (``n_a + 1`` per axis, the last axis in groups
        of ``G``), so the upper boundary faces of non-periodic axes get words of their own.
        """
        lin = ti.u32(0)
        for a in ti.static(range(self.dim)):
            if ti.static(a == self.dim - 1):
                lin = lin * ti.u32(-(-(self.n[a] + 1) // self.group)) + ti.u32(J[a + 1] // self.group)
            else:
                lin = lin * ti.u32(self.n[a] + 1) + ti.u32(J[a + 1])
        member = rng.member_word(self.key, self.member0, J[0])
        return rng.philox4x32(ti.math.uvec4(lin, step, member, ti.u32(rng.FACE_NOISE)), key)

    @ti.func
    def _face_flux(self, J, a: ti.template(), bits):
        """Total flux F (eq. 8) through the lower face of cell ``J`` along axis ``a``."""
        F = self.real(0.0)
        if face_kind(self.grid, J[a + 1], a) != NEUMANN:  # a Neumann wall carries no flux
            qq = self._pair(self.q, J, a, self.grid.reservoir)
            J0 = J
            J0[0] = 0
            root_sum = self.real(0.0)
            if ti.static(self.gaussian):  # q̄'s roots: once per cell for all members (the root pass)
                r = self._pair(self.root, J0, a, self.root_reservoir)
                root_sum = r[0] + r[1]
            else:
                root_sum = ti.sqrt(ti.max(qq[0], self.real(0.0))) + ti.sqrt(ti.max(qq[1], self.real(0.0)))
            F = self._flux(J0, a, qq[0], qq[1], root_sum, bits)
        return F

    @ti.func
    def _mean_flux(self, F, a: ti.template()):
        """The flux ½ Δq̄/Δx_a of eq. (10) through face ``F`` along axis ``a`` (``F`` indexes
        :attr:`flux`: a cell's lower face, or the upper boundary face ``n_a``); none through a
        Neumann wall."""
        v = self.real(0.0)
        if face_kind(self.grid, F[a + 1], a) != NEUMANN:
            s = self._pair(self.qbar, F, a, self.grid.reservoir)
            v = self._gradient(F, a, s[0], s[1])
        return v

    @ti.func
    def _gradient(self, F0, a: ti.template(), q_left, q_right):
        r"""The deterministic part of the flux through face ``F0`` (member index 0) along axis ``a``:
        ``½ (q_R − q_L)/Δx_a`` (eq. 8), or with a potential the Scharfetter–Gummel form
        ``½ (c_R q_R − c_L q_L)/Δx_a`` of :func:`drift_coefficients`, which vanishes on
        ``q ∝ e^{−Ū}`` (compiled in only with a potential: without one, the bits of eq. 8)."""
        v = self.real(0.0)
        if ti.static(self.drifting):
            c = self.coef[F0]
            v = self.real(0.5 / self.grid.dx[a]) * (c[2 * a + 1] * q_right - c[2 * a] * q_left)
        else:
            v = self.real(0.5 / self.grid.dx[a]) * (q_right - q_left)
        return v

    @ti.func
    def _flux(self, F0, a: ti.template(), q_left, q_right, root_sum, bits):
        """Eq. (8) through face ``F0`` (member index 0; ``i`` along axis ``a``) from the densities on
        its two sides and the sum of their amplitudes' square roots (:meth:`_gradient`: with the
        drift); a Dirichlet face adds what it carries to :attr:`inflow`."""
        i = F0[a + 1]
        F = self._gradient(F0, a, q_left, q_right) \
            + self.real(0.5 * self.noise_scale) * root_sum * rng.normal(bits, self.real)
        if ti.static(DIRICHLET in self.grid.boundary[a]):
            area = ti.static(self.grid.face_area[a] * self.dt)
            if i == 0:
                self.inflow[None] += -ti.cast(F, ti.f64) * area
            elif i == self.n[a]:
                self.inflow[None] += ti.cast(F, ti.f64) * area
        return F

    # -- the two parts of a step (one kernel: SPDESolver._flux_step) --------------------------
    @ti.func
    def fluxes(self, step):
        """First part of step ``step``: every face flux F of eq. (8) into :attr:`flux`, and the
        Dirichlet inflow they carry added to :attr:`inflow` (zeroed by the caller); q is not
        changed. Noise keyed on (seed, member, ``step``, face). With q̄, also the right-hand side
        of eq. (10) into :attr:`dqbar`, made at each cell from q̄'s fluxes through both its faces
        per axis (a scalar per cell where a field of face fluxes would take ``dim`` values, with
        the same bits)."""
        if ti.static(self.gaussian):
            for J in ti.grouped(self.root):  # q̄'s square roots, once per cell
                self.root[J] = ti.sqrt(ti.max(self.qbar[J], self.real(0.0)))
        for S in ti.grouped(ti.ndrange(self.ensemble, *self.groups[:-1], self.spread)):  # the rows along the last axis
            if S[S.n - 1] == 0:  # a row's other iterations are empty (grid.row_spread)
                for k in range(-(-self.groups[-1] // self.lanes)):  # serially along the row
                    self._group_fluxes(_row_cell(S, k), step)
        G, last = ti.static(self.group, self.dim)
        for a in ti.static(range(self.dim)):  # upper boundary faces (periodic ones are face 0)
            if ti.static(self.grid.boundary[a][1] != PERIODIC):
                for K in ti.grouped(ti.ndrange(*self.upper_layer[a])):
                    J = K
                    J[a + 1] = self.n[a]
                    bits = self._face_noise(J, step, ti.math.uvec2(self.key[0], self.key[1]))
                    w = (J[last] % G) * self.dim + a
                    word = bits[0]
                    for k in ti.static(range(1, 4)):
                        if w == k:
                            word = bits[k]
                    self.flux[J][a] = self._face_flux(J, a, word)

    @ti.func
    def _group_fluxes(self, K, step):
        """:meth:`fluxes` through the lower faces of the ``L`` counter groups ``K`` (``K[last]``
        counts them along the last axis) and q̄'s right-hand side at their cells. A row is one
        iteration of the parallel loop (one per group cost a quarter of the pass: RESULTS.md)."""
        G, last, L, n = ti.static(self.group, self.dim, self.lanes, self.n[-1])
        words = ti.Matrix.zero(ti.u32, L, 4)  # L groups of G cells along the last axis, Philox calls first
        live = ti.Vector.zero(ti.i32, L)
        for h in ti.static(range(L)):
            J = K
            J[last] = (K[last] * L + h) * G
            if J[last] < n and not self._inside_replaced(J):  # inside the replaced cells: no flux, no normal
                live[h] = 1
                bits = self._face_noise(J, step, ti.math.uvec2(self.key[0], self.key[1]))
                for w in ti.static(range(4)):
                    words[h, w] = bits[w]
        for h in ti.static(range(L)):
            if live[h]:
                I = K
                I[last] = (K[last] * L + h) * G
                for g in ti.static(range(G)):
                    if ti.static(G == 1) or I[last] < n:
                        for a in ti.static(range(self.dim)):
                            self.flux[I][a] = self._face_flux(I, a, words[h, g * self.dim + a])
                    I[last] += 1
        if ti.static(self.track_mean):
            if K[0] == 0:  # q̄'s right-hand side, both faces per axis (no face field)
                J = K
                J[last] = K[last] * L * G
                for g in ti.static(range(L * G)):
                    if J[last] < n:
                        dq = self.real(0.0)
                        for a in ti.static(range(self.dim)):
                            dq += (self._mean_flux(self.upper(J, a), a) - self._mean_flux(J, a)) \
                                * self.real(1.0 / self.grid.dx[a])
                        self.dqbar[J] = dq
                    J[last] += 1

    @ti.func
    def upper(self, J, a: ti.template()):
        """Index in :attr:`flux` of the upper face of cell ``J`` (member index first) along axis
        ``a``: :func:`grid.across` the upper face (periodic: face ``n_a`` is face 0)."""
        up, _ = across(self.grid, J, a, 1)
        return up

    @ti.func
    def _divergence(self, J):
        """Σ_a (F_{J+½e_a} − F_{J−½e_a}) / Δx_a: the right-hand side of eq. (9)."""
        dq = self.real(0.0)
        for a in ti.static(range(self.dim)):
            dq += (self.flux[self.upper(J, a)][a] - self.flux[J][a]) * self.real(1.0 / self.grid.dx[a])
        return dq

    @ti.func
    def update(self, diagnosing: ti.template(), n):
        r"""Second part: eq. (9), :math:`q_I \mathrel{+}= Δt \sum_a (F_{I+½e_a} - F_{I-½e_a}) / Δx_a`,
        with the fluxes of :meth:`fluxes` (and eq. 10 for q̄, in the same loop: one parallel task).
        A row along the last axis (``n`` cells) per working iteration of the
        parallel loop (:attr:`spread` iterations a row); with ``diagnosing``, also the sums of
        :meth:`~.fv.SPDESolver.diagnose` (zeroed by the caller) of the new q, one atomic per row.
        ``n`` is an argument, not a constant: LLVM unrolled a short constant row fully and (fast
        math) summed its last cell's divergence in another order with :attr:`replaced` than without."""
        for S in ti.grouped(ti.ndrange(self.ensemble, *self.n[:-1], self.spread)):
            if S[S.n - 1] == 0:  # a row's other iterations are empty (grid.row_spread)
                mass, q_min, negative = 0.0, self.real(ti.math.inf), 0
                for i in range(n):
                    J = _row_cell(S, i)
                    replaced = False
                    if ti.static(self.replacing):
                        replaced = self.replaced[J] != 0
                    q = self.q[J]  # `=`, not `+=`, below: on a field `+=` is an atomic add (a compare-and-swap loop)
                    self.q[J] = ti.select(replaced, q, q + self.real(self.dt) * self._divergence(J))
                    if ti.static(self.track_mean):
                        if J[0] == 0:  # q̄ has one member
                            self.qbar[J] = self.qbar[J] + self.real(self.dt) * self.dqbar[J]  # (not atomic)
                    if ti.static(diagnosing):
                        qn = self.q[J]
                        mass += ti.cast(qn, ti.f64)
                        q_min = ti.min(q_min, qn)
                        negative += ti.cast(qn < 0, ti.i32)
                if ti.static(diagnosing):
                    self.mass[None] += mass * ti.static(self.grid.cell_volume)
                    ti.atomic_min(self.q_min[None], q_min)
                    self.n_negative[None] += negative


@ti.func
def _row_cell(S, i):
    """The index of entry ``i`` along the last axis of the row whose other indices are ``S``'s but
    its last (the iteration within the row's spread: :func:`~..core.grid.row_spread`)."""
    return ti.Vector([S[c] for c in ti.static(range(S.n - 1))] + [i])


# ---------------------------------------------------------------------------------------
# the drift of an external potential (NumPy, once per run)
# ---------------------------------------------------------------------------------------
def bernoulli(z: np.ndarray) -> np.ndarray:
    """B(z) = z / (e^z − 1), B(0) = 1 (the Scharfetter–Gummel weight)."""
    z = np.asarray(z, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return np.where(z == 0, 1.0, z / np.where(z == 0, 1.0, np.expm1(z)))


def drift_coefficients(grid) -> np.ndarray:
    r"""``(*faces, 2 dim)``: the Scharfetter–Gummel weights ``c_L = B(δ)``, ``c_R = B(−δ) = B(δ) + δ``,
    ``δ = Ū_R − Ū_L``, of each face (the lower face of each cell along axis ``a`` in entries
    ``2a, 2a + 1``; the padded last layer holds the upper boundary faces), so that the deterministic
    flux ``½ (c_R q_R − c_L q_L)/Δx_a = ½ e^{−U_f} Δ(q e^{Ū})/Δx_a`` with ``e^{−U_f}`` the
    reciprocal logarithmic mean of ``e^{Ū}`` on the two sides: exact for a potential linear across
    the face, and zero on ``q ∝ e^{−Ū}`` at any Péclet number. ``Ū`` is
    :meth:`~ti_dk.core.expr.Potential.cell_values` (cell averages of e^{−U}, so the discrete
    equilibrium is the cell-averaged Boltzmann profile); a reservoir cell beyond a Dirichlet side
    has its own Ū; periodic sides wrap. Weights of faces that carry no flux (Neumann, the padded
    layer of other axes) are 1. Made once per grid and kept with the potential
    (:meth:`~ti_dk.core.expr.Potential.derived`: the time-step check and the solver read the same, read-only)."""
    return grid.potential.derived(("drift_coefficients", grid.cells, grid.lengths, grid.boundary),
                                  lambda: _weights(grid))


def _weights(grid) -> np.ndarray:
    """:func:`drift_coefficients`, made."""
    n, dim = grid.cells, grid.dim
    ub = grid.potential.cell_values(n, grid.lengths, pad=1).copy()  # the periodic images are written in
    for a, (lo, _hi) in enumerate(grid.boundary):
        if lo == PERIODIC:
            take = lambda i: tuple(i if b == a else slice(None) for b in range(dim))  # noqa: E731
            ub[take(0)], ub[take(n[a] + 1)] = ub[take(n[a])], ub[take(1)]
    out = np.ones((*(m + 1 for m in n), 2 * dim))
    for a in range(dim):
        inner = [slice(1, m + 1) for m in n]
        left = ub[tuple(slice(0, n[a] + 1) if b == a else inner[b] for b in range(dim))]
        right = ub[tuple(slice(1, n[a] + 2) if b == a else inner[b] for b in range(dim))]
        with np.errstate(invalid="ignore"):
            d = right - left
        c = bernoulli(d)
        at = tuple(slice(0, n[a] + 1) if b == a else slice(0, m) for b, m in enumerate(n))
        out[at + (2 * a,)], out[at + (2 * a + 1,)] = c, c + d
        for side, face in enumerate((0, n[a])):
            if grid.boundary[a][side] == NEUMANN:
                out[tuple(face if b == a else slice(None) for b in range(dim)) + (slice(2 * a, 2 * a + 2),)] = 1.0
    return out


def stability_number(grid, dt: float) -> float:
    r"""``max_I Σ_a Δt/(2Δx_a²) (c_L^{I+½e_a} + c_R^{I−½e_a})``: the explicit scheme's diagonal, which
    must stay below 1; without a potential (``grid.potential`` None: a :class:`~ti_dk.core.grid.Grid`
    or a scene's ``[grid]``) ``Σ_a Δt/Δx_a²``, and the drift raises it near steep slopes, by about
    ``Δt |∂_aU| / (2Δx_a)``. The one stability number: the scene checks read it."""
    if grid.potential is None:
        return sum(dt / h**2 for h in grid.dx)
    coef = drift_coefficients(grid)
    total = 0.0
    for a, (n, h) in enumerate(zip(grid.cells, grid.dx)):
        inner = tuple(slice(0, m) for m in grid.cells)
        up = tuple(slice(1, n + 1) if b == a else s for b, s in enumerate(inner))
        total = total + dt / (2 * h * h) * (coef[up + (2 * a,)] + coef[inner + (2 * a + 1,)])
    return float(np.max(total))
