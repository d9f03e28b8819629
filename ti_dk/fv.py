"""Finite-volume Dean–Kawasaki (paper eq. 7–9) and its linearised Gaussian version (eq. 10–11)."""

import math

import numpy as np
import taichi as ti

from . import rng
from .grid import DIRICHLET, NEUMANN, PERIODIC, Grid, across, face_kind, numpy_dtype
from .solver import Solver


@ti.data_oriented
class SPDESolver(Solver):
    r"""Explicit Euler–Maruyama for ``dq = ½∇²q dt + ∇·(√max(q,0) dW)`` on every ensemble member.

    One step is the flux form, eq. (9),

    .. math:: q_I^{n+1} = q_I^n + Δt \sum_a \frac{F_{I+½e_a} - F_{I-½e_a}}{Δx_a},

    with the total face flux of eq. (8),

    .. math:: F_{I-½e_a} = \frac{q_I - q_{I-e_a}}{2Δx_a} + \frac{A(s_{I-e_a}, s_I)}{\sqrt{Δt V_c}} Z,
              \quad A(s_1, s_2) = \frac{\sqrt{\max(s_1,0)} + \sqrt{\max(s_2,0)}}{2},

    where ``s = q`` for the finite-volume scheme (eq. 7) and ``s = q̄`` for the linearised Gaussian
    scheme (eq. 11), q̄ obeying the deterministic heat equation (10). ``Z`` is a standard normal
    keyed on (seed, member, step, face), so a face's noise is the same whoever computes it: one
    Philox-4x32-10 counter serves ``G = 4 // dim`` consecutive cells along the last axis (4 in 1D,
    2 in 2D, 1 in 3D), word ``g·dim + a`` driving the lower face along axis ``a`` of the group's
    cell ``g``, so all four words are used in 1D and 2D (three in 3D). This numbering replaced one
    counter per cell (issue 13); it changed the 1D and 2D noise streams, not the 3D one.
    For the finite-volume scheme ``√max(q, 0)`` is taken on both sides of each face as the flux is
    made (measured: as fast as loading roots from a pass before, and that pass, 7 % of the 2D step,
    and its field are gone); for the Gaussian scheme q̄'s roots are taken once per cell for all
    members.

    Boundaries: periodic faces wrap; Neumann faces carry no flux; a Dirichlet face sees a ghost
    cell at the reservoir density (for q and for q̄).
    """

    def __init__(self, grid: Grid, dt: float, ensemble: int, key: tuple[int, int], real=ti.f64, gaussian: bool = False,
                 member0: int = 0, track_mean: bool = False):
        self.grid, self.dt, self.ensemble, self.real, self.gaussian = grid, dt, ensemble, real, gaussian
        # q̄ (eq. 10) is advanced for the Gaussian scheme's amplitude, or for whoever reads it (the hybrid's ghosts)
        self.track_mean = gaussian or track_mean
        self.member0 = member0  # global index of member 0: a member's noise depends on it, not on the chunking
        self.dim = grid.dim
        self.n = grid.cells
        self.key = key  # the Philox key of the run (rng.seed_key of its seed)
        rng.prepare()
        self.group = max(1, 4 // self.dim)  # cells along the last axis sharing one Philox counter
        self.lanes = rng.lanes(self.dim)  # counter groups a flux loop iteration takes
        # counter groups per member: the last axis of the padded face grid cut into groups of `group`
        self.groups = (*self.n[:-1], -(-self.n[-1] // self.group))
        self.noise_scale = 1.0 / (dt * grid.cell_volume) ** 0.5  # 1/√(Δt V_c) of eq. (7)
        # the layer of upper boundary faces along each axis, member index first
        self.upper_layer = [(ensemble, *(1 if b == a else m for b, m in enumerate(self.n))) for a in range(self.dim)]
        faces = tuple(m + 1 for m in self.n)
        self.q = ti.field(real, shape=(ensemble, *self.n))  # number density q_I [particles / volume]
        # total flux F (eq. 8) through the lower face of each cell, one component per axis
        # [particles / (area · time)]; the padded last layer holds the upper boundary faces
        self.flux = ti.Vector.field(self.dim, real, shape=(ensemble, *faces))
        if gaussian:  # √max(q̄, 0) of every cell, shared by all members [√(particles / volume)]
            self.root = ti.field(real, shape=(1, *self.n))
            self.root_reservoir = tuple(tuple(math.sqrt(max(r, 0.0)) for r in side) for side in grid.reservoir)
        if self.track_mean:
            self.qbar = ti.field(real, shape=(1, *self.n))  # deterministic density q̄ (eq. 10) [particles / volume]
            self.dqbar = ti.field(real, shape=(1, *self.n))  # Σ_a (F̄_{I+½e_a} − F̄_{I−½e_a}) / Δx_a of eq. (10) [particles / (volume · time)]
        self.mass = ti.field(ti.f64, shape=())  # Σ over members and cells of q V_c after the step [particles]
        self.q_min = ti.field(real, shape=())  # smallest q over members and cells [particles / volume]
        self.n_negative = ti.field(ti.i64, shape=())  # cells (over all members) with q < 0
        self.inflow = ti.field(ti.f64, shape=())  # particles entering through Dirichlet sides this step
        self.replaced = None  # u8 field like q: 1 where the caller overwrites q after each step (see replaced_in)

    # -- public -------------------------------------------------------------------------
    def initialize(self, ppc: np.ndarray) -> None:
        """Set every member (and q̄) to ``ppc`` particles per cell."""
        q0 = np.broadcast_to(ppc / self.grid.cell_volume, (self.ensemble, *self.n))
        self.q.from_numpy(np.ascontiguousarray(q0, dtype=numpy_dtype(self.real)))
        if self.track_mean:
            self.qbar.from_numpy(np.ascontiguousarray(q0[:1], dtype=numpy_dtype(self.real)))

    def replaced_in(self, mask) -> None:
        """Declare that after every step the caller overwrites q wherever the u8 field ``mask``
        (shaped like q) is 1, from something else (the hybrid's covered cells take their particle
        counts, eq. 12): the step then skips what only those cells read, the update of such a cell
        and the fluxes (and their normals) of a group of ``G`` cells whose lower faces all have
        such cells on both sides. Every other cell's q and every other face's flux keep their bits
        (each face's noise is keyed on the face); q̄ may round differently in the last bit (fast
        math compiles the kernel anew). Call before the first step (the kernels compile the
        choice in). sphere3d: a third of the cells are such, the hybrid's flux pass 81 → 69 ms
        (medians of 12)."""
        self.replaced = mask

    @property
    def replacing(self) -> bool:
        """Whether :meth:`replaced_in` was called (for ``ti.static``: Taichi scope takes no ``is not None``)."""
        return self.replaced is not None

    def step(self, n: int) -> None:
        """Advance all members from step ``n`` to ``n + 1``."""
        if self.dim == 1 and not self.track_mean:
            self._step_members(n)
        else:
            self.fluxes(n)
            self.update()
            self.diagnose()

    def state(self) -> dict[str, np.ndarray]:
        """The fields a checkpoint needs to continue bit for bit."""
        return {"q": self.q.to_numpy(), **({"qbar": self.qbar.to_numpy()} if self.track_mean else {})}

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        self.q.from_numpy(st["q"])
        if self.track_mean:
            self.qbar.from_numpy(st["qbar"])
        self.diagnose()

    def density(self) -> np.ndarray:
        """Number density of every member, ``(ensemble, *cells)``, float64 (a fresh array: callers may change it)."""
        return self.q.to_numpy().astype(np.float64, copy=False)

    def diagnostics(self) -> dict[str, float]:
        return {"mass": self.mass[None], "min_density": float(self.q_min[None]),
                "negative_cells": int(self.n_negative[None]), "boundary_inflow": self.inflow[None], "clamped_steps": 0}

    # -- kernels ------------------------------------------------------------------------
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
    def _face_noise(self, J, step):
        """The four Philox words of the counter group holding cell ``J`` (member index first).

        Groups are numbered on the padded face grid (``n_a + 1`` per axis, the last axis in groups
        of ``G``), so the upper boundary faces of non-periodic axes get words of their own.
        """
        lin = ti.u32(0)
        for a in ti.static(range(self.dim)):
            if ti.static(a == self.dim - 1):
                lin = lin * ti.u32(-(-(self.n[a] + 1) // self.group)) + ti.u32(J[a + 1] // self.group)
            else:
                lin = lin * ti.u32(self.n[a] + 1) + ti.u32(J[a + 1])
        return rng.philox4x32(ti.math.uvec4(lin, step, ti.u32(J[0] + self.member0), ti.u32(rng.FACE_NOISE)),
                              ti.math.uvec2(self.key[0], self.key[1]))

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
            F = self._flux(J[a + 1], a, qq[0], qq[1], root_sum, bits)
        return F

    @ti.func
    def _mean_flux(self, F, a: ti.template()):
        """The flux ½ Δq̄/Δx_a of eq. (10) through face ``F`` along axis ``a`` (``F`` indexes
        :attr:`flux`: a cell's lower face, or the upper boundary face ``n_a``); none through a
        Neumann wall."""
        v = self.real(0.0)
        if face_kind(self.grid, F[a + 1], a) != NEUMANN:
            s = self._pair(self.qbar, F, a, self.grid.reservoir)
            v = self.real(0.5 / self.grid.dx[a]) * (s[1] - s[0])
        return v

    @ti.func
    def _flux(self, i, a: ti.template(), q_left, q_right, root_sum, bits):
        """Eq. (8) through face ``i`` along axis ``a`` from the densities on its two sides and the
        sum of their amplitudes' square roots; a Dirichlet face adds what it carries to :attr:`inflow`."""
        F = self.real(0.5 / self.grid.dx[a]) * (q_right - q_left) \
            + self.real(0.5 * self.noise_scale) * root_sum * rng.normal(bits, self.real)
        if ti.static(DIRICHLET in self.grid.boundary[a]):
            area = ti.static(self.grid.face_area[a] * self.dt)
            if i == 0:
                self.inflow[None] += -ti.cast(F, ti.f64) * area
            elif i == self.n[a]:
                self.inflow[None] += ti.cast(F, ti.f64) * area
        return F

    # -- the split step (public: the hybrid runs its particles between these) ------------
    @ti.kernel
    def fluxes(self, step: ti.u32):
        """First part of step ``step``: every face flux F of eq. (8) into :attr:`flux`, and the
        Dirichlet inflow they carry into :attr:`inflow`; q is not changed. Noise keyed on (seed,
        member, ``step``, face). With q̄, also the right-hand side of eq. (10) into :attr:`dqbar`,
        made at each cell from q̄'s fluxes through both its faces per axis (a scalar per cell
        where a field of face fluxes took ``dim`` values: 35 MB less at 128³, in the same time and
        with the same bits in the pinned runs)."""
        self.inflow[None] = 0.0
        if ti.static(self.gaussian):
            for J in ti.grouped(self.root):  # q̄'s square roots, once per cell
                self.root[J] = ti.sqrt(ti.max(self.qbar[J], self.real(0.0)))
        G, last, L, n = ti.static(self.group, self.dim, self.lanes, self.n[-1])
        for K in ti.grouped(ti.ndrange(self.ensemble, *self.groups[:-1], -(-self.groups[-1] // L))):
            words = ti.Matrix.zero(ti.u32, L, 4)  # L groups of G cells along the last axis, Philox calls first
            live = ti.Vector.zero(ti.i32, L)
            for h in ti.static(range(L)):
                J = K
                J[last] = (K[last] * L + h) * G
                if J[last] < n and not self._inside_replaced(J):  # inside the replaced cells: no flux, no normal
                    live[h] = 1
                    bits = self._face_noise(J, step)
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
        for a in ti.static(range(self.dim)):  # upper boundary faces (periodic ones are face 0)
            if ti.static(self.grid.boundary[a][1] != PERIODIC):
                for K in ti.grouped(ti.ndrange(*self.upper_layer[a])):
                    J = K
                    J[a + 1] = self.n[a]
                    bits = self._face_noise(J, step)
                    w = (J[last] % G) * self.dim + a
                    word = bits[0]
                    for k in ti.static(range(1, 4)):
                        if w == k:
                            word = bits[k]
                    self.flux[J][a] = self._face_flux(J, a, word)

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

    @ti.kernel
    def update(self):
        r"""Second part: eq. (9), :math:`q_I \mathrel{+}= Δt \sum_a (F_{I+½e_a} - F_{I-½e_a}) / Δx_a`,
        with the fluxes of the last :meth:`fluxes` (and eq. 10 for q̄, in the same loop: one
        parallel task, see :func:`grid.exclusive_scan`)."""
        for J in ti.grouped(self.q):
            replaced = False
            if ti.static(self.replacing):
                replaced = self.replaced[J] != 0
            if not replaced:
                self.q[J] += self.real(self.dt) * self._divergence(J)
            if ti.static(self.track_mean):
                if J[0] == 0:  # q̄ has one member
                    self.qbar[J] += self.real(self.dt) * self.dqbar[J]

    @ti.kernel
    def _step_members(self, step: ti.u32):
        """The 1D finite-volume step (:meth:`fluxes`, :meth:`update`, :meth:`diagnose`) in one pass
        over each member's faces: face ``i``'s flux (eq. 8) is made from the old densities of cells
        ``i − 1`` and ``i``, held in registers with their roots, and then cell ``i − 1`` is updated
        (eq. 9) from it and the flux of face ``i − 1``; so each cell is read and written once, and
        a member's diagnostics are summed locally with one atomic per member. Same bits as the
        three-kernel step (tested); issue 13: this replaced four passes over the member."""
        n, G = ti.static(self.n[0], self.group)
        lo, hi = ti.static(self.grid.boundary[0])
        res_lo, res_hi = ti.static(self.grid.reservoir[0])
        vol = ti.static(self.grid.cell_volume)
        self.inflow[None] = 0.0
        self.mass[None] = 0.0
        self.q_min[None] = self.real(ti.math.inf)
        self.n_negative[None] = 0
        for e in range(self.ensemble):
            q_left, root_left = self.real(0.0), self.real(0.0)  # cell i − 1 (old value) and its root
            if ti.static(lo == PERIODIC):
                q_left = self.q[e, n - 1]
            elif ti.static(lo == DIRICHLET):
                q_left = self.real(res_lo)
            root_left = ti.sqrt(ti.max(q_left, self.real(0.0)))
            F_left, F_first = self.real(0.0), self.real(0.0)  # fluxes of face i − 1 and face 0
            mass, q_min, negative = 0.0, self.real(ti.math.inf), 0
            for k in range((n + G) // G):  # faces 0 … n, G per Philox counter
                bits = self._face_noise(ti.Vector([e, G * k]), step)
                for g in ti.static(range(G)):
                    i = G * k + g
                    if i <= n:
                        q_right = self.real(0.0)
                        if i < n:
                            q_right = self.q[e, i]
                        elif ti.static(hi == DIRICHLET):
                            q_right = self.real(res_hi)
                        root_right = ti.sqrt(ti.max(q_right, self.real(0.0)))
                        F = self.real(0.0)  # what a Neumann face carries
                        if i == n and ti.static(hi == PERIODIC):
                            F = F_first
                        elif not ((i == 0 and ti.static(lo == NEUMANN)) or (i == n and ti.static(hi == NEUMANN))):
                            F = self._flux(i, 0, q_left, q_right, root_left + root_right, bits[g])
                        if i == 0:
                            F_first = F
                        else:  # eq. (9) for cell i − 1
                            qn = q_left + self.real(self.dt) * ((F - F_left) * self.real(1.0 / self.grid.dx[0]))
                            self.q[e, i - 1] = qn
                            mass += ti.cast(qn, ti.f64)
                            q_min = ti.min(q_min, qn)
                            negative += ti.cast(qn < 0, ti.i32)
                        q_left, root_left, F_left = q_right, root_right, F
            self.mass[None] += mass * vol
            ti.atomic_min(self.q_min[None], q_min)
            self.n_negative[None] += negative

    @ti.kernel
    def diagnose(self):
        """Mass, smallest density and negative cells of q as it stands (after a step or a hybrid sync)."""
        vol = ti.static(self.grid.cell_volume)
        self.mass[None] = 0.0
        self.q_min[None] = self.real(ti.math.inf)
        self.n_negative[None] = 0
        for J in ti.grouped(self.q):
            qn = self.q[J]
            self.mass[None] += ti.cast(qn, ti.f64) * vol
            ti.atomic_min(self.q_min[None], qn)
            self.n_negative[None] += ti.cast(qn < 0, ti.i64)
