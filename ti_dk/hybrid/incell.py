"""Where in its cell a particle the hybrid samples lies (paper §3; with a potential, its Boltzmann profile in the cell): the
slope of the profile density (``ghost_profile``) and the placement along it."""

import numpy as np
import taichi as ti

from ..core import rng
from ..core.grid import DIRICHLET, across
from ..methods.particles import Walker
from .region import Region

PROFILE_PIECES = 4  # with a potential: pieces per cell and axis of the in-cell Boltzmann profile (InCell.place)


@ti.data_oriented
class InCell:
    """The in-cell profile of :class:`~.ghosts.Sampler`'s particles: :meth:`tilt` reads its slope
    per axis from the profile density (q̄ with ``mean``, the member's q with ``linear``; none with
    ``uniform``), :meth:`place` draws a position. With a potential the profile follows e^{−U}
    within the cell (:attr:`nodes`, ``dim × (PROFILE_PIECES + 1)`` numbers a cell, made once)."""

    def __init__(self, spde, region: Region, walker: Walker, profile: str):
        self.spde, self.region, self.walker, self.profile = spde, region, walker, profile
        self.grid, self.dim, self.n, self.real = spde.grid, spde.dim, spde.n, spde.real
        assert profile != "mean" or spde.track_mean, "ghost_profile 'mean' reads the SPDE's q̄"
        self.shaped = walker.drifting and profile != "uniform"  # placed along e^{-U} within the cell (place)
        if self.shaped:
            # per cell and axis: −ln of e^{−U}'s marginal at the PROFILE_PIECES + 1 points from the lower
            # face to the upper one, less the cell's Ū [k_BT] (Potential.axis_profiles)
            self.nodes = ti.Matrix.field(self.dim, PROFILE_PIECES + 1, spde.real, shape=self.n)
            nodes = spde.grid.potential.axis_profiles(self.n, spde.grid.lengths, PROFILE_PIECES)
            nodes = np.clip(np.nan_to_num(nodes, nan=0.0, posinf=500.0, neginf=-500.0), -500.0, 500.0)  # (e^{−500}: none)
            self.nodes.from_numpy(nodes.astype(np.float32 if spde.real == ti.f32 else np.float64))

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

        Which ``p`` (``ghost_profile``), measured on the paper's void case:

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
        as the double well's crossing rate showed.)
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
                    u = ti.min((self.real(piece) + t) * self.real(1.0 / P), self.real(1.0 - 2.0**-24))  # inside the cell
                    y[a] = (self.real(C[a]) + u) * self.real(self.grid.dx[a])
            else:
                y = self.walker.in_cell(C, bits, tilt)
        else:
            y = self.walker.in_cell(C, bits, tilt)
        return y
