"""The flux through one face of the finite-volume Dean–Kawasaki scheme and its Gaussian version
(paper eq. 8, 10): :class:`Faces`, the part of :class:`~.fv.SPDESolver` that makes it from the two
sides of the face and its normal; and the drift of an external potential in it, the
Scharfetter–Gummel weights of each face (:func:`drift_coefficients`, NumPy, once per run)."""

import numpy as np
import taichi as ti

from ..core import rng
from ..core.grid import DIRICHLET, NEUMANN, PERIODIC, across, face_kind


@ti.data_oriented
class Faces:
    r"""Eq. (8) through one face, and eq. (10)'s flux of q̄, as ``ti.func``\ s on the fields of
    ``solver`` (an :class:`~.fv.SPDESolver`: its densities, square roots, weights ``coef`` and
    Dirichlet ``inflow``): the values on the two sides of a face (:meth:`pair`), the Philox words
    of its normal (:meth:`noise`, keyed on seed, member, step and face), its deterministic part
    (:meth:`gradient`, with the drift) and its total (:meth:`flux`, :meth:`face_flux`).

    One Philox-4x32-10 counter serves ``G = 4 // dim`` consecutive cells along the last axis (4 in
    1D, 2 in 2D, 1 in 3D), word ``g·dim + a`` driving the lower face along axis ``a`` of the group's
    cell ``g``, so all four words are used in 1D and 2D (three in 3D). For the finite-volume scheme
    ``√max(q, 0)`` is taken on both sides of each face as the flux is made (as fast as loading
    roots made by a pass before, which saves that pass and its field); for the Gaussian scheme q̄'s
    roots are taken once per cell for all members."""

    def __init__(self, solver):
        self.solver = solver

    @ti.func
    def pair(self, f: ti.template(), J, a: ti.template(), reservoir: ti.template()):
        """Values of ``f`` left and right of the lower face of cell ``J`` along axis ``a``.

        ``J`` carries the member index first; the left cell is :func:`grid.across` the face (a
        periodic image), or beyond a side the Dirichlet reservoir value ``reservoir[a]`` (the
        density, or its square root); so is the right one of the upper boundary face ``n_a``.
        """
        fv = self.solver
        res_lo, res_hi = ti.static(reservoir[a])
        L, has_left = across(fv.grid, J, a, 0)
        v = ti.Vector([fv.real(0.0), fv.real(0.0)])
        if not has_left:
            v = ti.Vector([fv.real(res_lo), f[J]])
        elif J[a + 1] == ti.static(fv.n[a]):
            v = ti.Vector([f[L], fv.real(res_hi)])
        else:
            v = ti.Vector([f[L], f[J]])
        return v

    @ti.func
    def noise(self, J, step, key):
        """The four Philox words of the counter group holding cell ``J`` (member index first), under
        ``key`` (the solver's key's two words, which a loop may read once before it: see
        ``SPDESolver._step_members``).

        Groups are numbered on the padded face grid (``n_a + 1`` per axis, the last axis in groups
        of ``G``), so the upper boundary faces of non-periodic axes get words of their own.
        """
        fv = self.solver
        lin = ti.u32(0)
        for a in ti.static(range(fv.dim)):
            if ti.static(a == fv.dim - 1):
                lin = lin * ti.u32(-(-(fv.n[a] + 1) // fv.group)) + ti.u32(J[a + 1] // fv.group)
            else:
                lin = lin * ti.u32(fv.n[a] + 1) + ti.u32(J[a + 1])
        member = rng.member_word(fv.key, fv.member0, J[0])
        return rng.philox4x32(ti.math.uvec4(lin, step, member, ti.u32(rng.FACE_NOISE)), key)

    @ti.func
    def face_flux(self, J, a: ti.template(), bits):
        """Total flux F (eq. 8) through the lower face of cell ``J`` along axis ``a``."""
        fv = self.solver
        F = fv.real(0.0)
        if face_kind(fv.grid, J[a + 1], a) != NEUMANN:  # a Neumann wall carries no flux
            qq = self.pair(fv.q, J, a, fv.grid.reservoir)
            J0 = J
            J0[0] = 0
            root_sum = fv.real(0.0)
            if ti.static(fv.gaussian):  # q̄'s roots: once per cell for all members (the root pass)
                r = self.pair(fv.root, J0, a, fv.root_reservoir)
                root_sum = r[0] + r[1]
            else:
                root_sum = ti.sqrt(ti.max(qq[0], fv.real(0.0))) + ti.sqrt(ti.max(qq[1], fv.real(0.0)))
            F = self.flux(J0, a, qq[0], qq[1], root_sum, bits)
        return F

    @ti.func
    def mean_flux(self, F, a: ti.template()):
        """The flux ½ Δq̄/Δx_a of eq. (10) through face ``F`` along axis ``a`` (``F`` indexes
        the solver's :attr:`~.fv.SPDESolver.flux`: a cell's lower face, or the upper boundary face ``n_a``); none through a
        Neumann wall."""
        fv = self.solver
        v = fv.real(0.0)
        if face_kind(fv.grid, F[a + 1], a) != NEUMANN:
            side = self.pair(fv.qbar, F, a, fv.grid.reservoir)
            v = self.gradient(F, a, side[0], side[1])
        return v

    @ti.func
    def gradient(self, F0, a: ti.template(), q_left, q_right):
        r"""The deterministic part of the flux through face ``F0`` (member index 0) along axis ``a``:
        ``½ (q_R − q_L)/Δx_a`` (eq. 8), or with a potential the Scharfetter–Gummel form
        ``½ (c_R q_R − c_L q_L)/Δx_a`` of :func:`drift_coefficients`, which vanishes on
        ``q ∝ e^{−Ū}`` (compiled in only with a potential: without one, the bits of eq. 8)."""
        fv = self.solver
        v = fv.real(0.0)
        if ti.static(fv.drifting):
            c = fv.coef[F0]
            v = fv.real(0.5 / fv.grid.dx[a]) * (c[2 * a + 1] * q_right - c[2 * a] * q_left)
        else:
            v = fv.real(0.5 / fv.grid.dx[a]) * (q_right - q_left)
        return v

    @ti.func
    def flux(self, F0, a: ti.template(), q_left, q_right, root_sum, bits):
        """Eq. (8) through face ``F0`` (member index 0; ``i`` along axis ``a``) from the densities on
        its two sides and the sum of their amplitudes' square roots (:meth:`gradient`: with the
        drift); a Dirichlet face adds what it carries to the solver's :attr:`~.fv.SPDESolver.inflow`."""
        fv = self.solver
        i = F0[a + 1]
        F = self.gradient(F0, a, q_left, q_right) \
            + fv.real(0.5 * fv.noise_scale) * root_sum * rng.normal(bits, fv.real)
        if ti.static(DIRICHLET in fv.grid.boundary[a]):
            area = ti.static(fv.grid.face_area[a] * fv.dt)
            if i == 0:
                fv.inflow[None] += -ti.cast(F, ti.f64) * area
            elif i == fv.n[a]:
                fv.inflow[None] += ti.cast(F, ti.f64) * area
        return F


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
