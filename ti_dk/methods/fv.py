"""Finite-volume Dean–Kawasaki (paper eq. 7–9) and its linearised Gaussian version (eq. 10–11)."""

import math

import numpy as np
import taichi as ti

from ..core import rng
from ..core.grid import DIRICHLET, NEUMANN, PERIODIC, Grid, across, numpy_dtype, row_spread
from .fluxes import Faces, drift_coefficients
from .passes import Passes
from .records import Scalars
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
    keyed on (seed, member, step, face), so a face's noise is the same whoever computes it
    (:class:`.fluxes.Faces` makes a face's flux, :class:`.passes.Passes` runs a step's two passes).

    Boundaries: periodic faces wrap; Neumann faces carry no flux; a Dirichlet face sees a ghost
    cell at the reservoir density (for q and for q̄).

    An external potential U (``grid.potential``) adds the drift of
    ``dq = ∇·(½∇q + ½ q∇U) dt + ∇·(√max(q,0) dW)``: the deterministic flux becomes the
    Scharfetter–Gummel form ``½ (c_R q_R − c_L q_L)/Δx_a`` (:func:`.fluxes.drift_coefficients`,
    weights per face in :attr:`coef`), for q and q̄ alike, so the deterministic scheme keeps the
    cell-averaged Boltzmann profile e^{−Ū} stationary to round-off; the noise is unchanged. A
    reservoir cell beyond a Dirichlet side holds ``reservoir_ppc`` particles at its own Ū.

    Build it with :func:`ti_dk.make_solver`, which also initialises it.

    Parameters
    ----------
    grid : Grid
        The cells, their boundaries and reservoirs, and the potential.
    dt : float
        The time step.
    ensemble : int
        Independent members, stepped together.
    key : ti.Field or tuple of int
        The run's Philox key, as :func:`ti_dk.core.rng.device_key` makes it (two words of a
        :func:`~ti_dk.core.rng.seed_key` also serve, compiled into the kernels).
    real : Taichi type
        ``ti.f64`` or ``ti.f32``: the precision of q, q̄ and the fluxes.
    gaussian : bool
        The linearised Gaussian scheme (eq. 11) instead of the finite-volume one (eq. 7).
    member0 : int
        The global index of member 0: a member's noise depends on it, not on how the ensemble
        is cut into chunks.
    track_mean : bool
        Advance q̄ (eq. 10) beside q for another reader (the hybrid's ghosts); the Gaussian scheme
        always does.
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
        self.lanes = rng.lanes(self.dim, flux=True)  # counter groups a flux loop iteration takes
        # counter groups per member: the last axis of the padded face grid cut into groups of `group`
        self.groups = (*self.n[:-1], -(-self.n[-1] // self.group))
        self.spread = row_spread(ensemble * math.prod(self.n[:-1]))  # iterations a row in the row loops
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
        self.scalars = Scalars([self.mass, self.q_min, self.n_negative, self.inflow])  # the four, read together
        self.drifting = grid.potential is not None  # an external potential's drift is compiled in
        if self.drifting:  # Scharfetter–Gummel weights (c_L, c_R) per axis of each face, shared by all members
            self.coef = ti.Vector.field(2 * self.dim, real, shape=(1, *faces))
            self.coef.from_numpy(drift_coefficients(grid)[None].astype(numpy_dtype(real)))
        self.replaced = None  # u8 field like q: 1 where the caller overwrites q after each step (see replaced_in)
        self.faces, self.passes = Faces(self), Passes(self)  # the flux through one face; the two passes of a step

    # -- public -------------------------------------------------------------------------
    def initialize(self, ppc: np.ndarray) -> None:
        """Set every member (and q̄) to ``ppc`` particles per cell."""
        q0 = np.broadcast_to(ppc / self.grid.cell_volume, (self.ensemble, *self.n))
        self.q.from_numpy(np.ascontiguousarray(q0, dtype=numpy_dtype(self.real)))
        if self.track_mean:
            self.qbar.from_numpy(np.ascontiguousarray(q0[:1], dtype=numpy_dtype(self.real)))

    def replaced_in(self, mask) -> None:
        """Declare that after every step the caller overwrites q where the u8 field ``mask`` (like q) is 1
        (the hybrid's covered cells take their counts, eq. 12): the step leaves such cells as they were
        and skips the fluxes (and normals) of a group of ``G`` cells whose lower faces all have such
        cells on both sides. Every other q and flux keeps its bits (noise is keyed per face); q̄ may
        round differently in the last bit. Call before the first step (the kernels compile it in)."""
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
            self._flux_step(n, self.n[-1], True)

    def state(self) -> dict[str, np.ndarray]:
        """The fields a checkpoint needs to continue bit for bit."""
        return {"q": self.q.to_numpy(), **({"qbar": self.qbar.to_numpy()} if self.track_mean else {})}

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """Continue from a :meth:`state` (q, and q̄ where tracked); the diagnostics recounted."""
        self.q.from_numpy(st["q"])
        if self.track_mean:
            self.qbar.from_numpy(st["qbar"])
        self.diagnose()

    def density(self) -> np.ndarray:
        """Number density of every member, ``(ensemble, *cells)``, float64 (a fresh array: callers may change it)."""
        return self.q.to_numpy().astype(np.float64, copy=False)

    def content(self) -> tuple:
        """``q`` [particles / volume], ``V_c``, no region (:meth:`Solver.content`)."""
        return self.q, self.grid.cell_volume, None

    def diagnostics(self, values=None) -> dict[str, float]:
        """After the last step: mass, the smallest density, negative cells, the Dirichlet inflow (``values``: read by a caller)."""
        mass, q_min, negative, inflow = map(float, self.scalars.read() if values is None else values)  # one read
        return {"mass": mass, "min_density": q_min, "negative_cells": int(negative), "boundary_inflow": inflow,
                "clamped_steps": 0}

    # -- kernels ------------------------------------------------------------------------
    @ti.kernel
    def _step_members(self, step: ti.u32):
        """The 1D finite-volume step (:meth:`.Passes.fluxes`, :meth:`.Passes.update`, :meth:`diagnose`) in one pass
        over each member's faces: face ``i``'s flux (eq. 8) is made from the old densities of cells
        ``i − 1`` and ``i``, held in registers with their roots, and then cell ``i − 1`` is updated
        (eq. 9) from it and the flux of face ``i − 1``; so each cell is read and written once, and
        a member's diagnostics are summed locally with one atomic per member. Same bits as the
        three-kernel step (tested)."""
        n, G = ti.static(self.n[0], self.group)
        lo, hi = ti.static(self.grid.boundary[0])
        res_lo, res_hi = ti.static(self.grid.reservoir[0])
        vol = ti.static(self.grid.cell_volume)
        self.inflow[None] = 0.0
        self.mass[None] = 0.0
        self.q_min[None] = self.real(ti.math.inf)
        self.n_negative[None] = 0
        for e, s in ti.ndrange(self.ensemble, self.spread):  # `spread` iterations a member (grid.row_spread)
            if s == 0:
                q_left, root_left = self.real(0.0), self.real(0.0)  # cell i − 1 (old value) and its root
                if ti.static(lo == PERIODIC):
                    q_left = self.q[e, n - 1]
                elif ti.static(lo == DIRICHLET):
                    q_left = self.real(res_lo)
                root_left = ti.sqrt(ti.max(q_left, self.real(0.0)))
                F_left, F_first = self.real(0.0), self.real(0.0)  # fluxes of face i − 1 and face 0
                mass, q_min, negative = 0.0, self.real(ti.math.inf), 0
                # the key read once a member: read at each call (a field the stores to q might alias,
                # for all LLVM knows) it cost 8 % of the step (benchmarks/RESULTS.md)
                key = ti.math.uvec2(self.key[0], self.key[1])
                for k in range((n + G) // G):  # faces 0 … n, G per Philox counter
                    bits = self.faces.noise(ti.Vector([e, G * k]), step, key)
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
                                F = self.faces.flux(ti.Vector([0, i]), 0, q_left, q_right, root_left + root_right, bits[g])
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

    def advance(self, n: int) -> None:
        """:meth:`.Passes.fluxes` then :meth:`.Passes.update` for step ``n``, in one kernel, without the diagnostics
        (the hybrid's step, which counts them after its synchronisation): one launch, not two."""
        self._flux_step(n, self.n[-1], False)

    @ti.kernel
    def _flux_step(self, step: ti.u32, n: ti.i32, diagnosing: ti.template()):
        """:meth:`.Passes.fluxes`, :meth:`.Passes.update` and (``diagnosing``) :meth:`diagnose` as one kernel: a
        launch costs tens of µs, a sizeable share of a 2D step on two threads."""
        self.inflow[None] = 0.0
        if ti.static(diagnosing):
            self.zero_diagnostics()
        self.passes.fluxes(step)
        self.passes.update(diagnosing, n)

    @ti.kernel
    def diagnose(self):
        """Mass, smallest density and negative cells of q as it stands (after a step or a hybrid sync)."""
        self.zero_diagnostics()
        for J in ti.grouped(self.q):
            self.diagnose_cell(J)

    @ti.func
    def upper(self, J, a: ti.template()):
        """Index in :attr:`flux` of the upper face of cell ``J`` (member index first) along axis
        ``a``: :func:`grid.across` the upper face (periodic: face ``n_a`` is face 0)."""
        up, _ = across(self.grid, J, a, 1)
        return up

    @ti.func
    def zero_diagnostics(self):
        """Zero the sums :meth:`diagnose_cell` adds to."""
        self.mass[None] = 0.0
        self.q_min[None] = self.real(ti.math.inf)
        self.n_negative[None] = 0

    @ti.func
    def diagnose_cell(self, J):
        """Add cell ``J`` to the sums of :meth:`diagnose`; returns its content ``q V_c`` (f64)."""
        qn = self.q[J]
        content = ti.cast(qn, ti.f64) * ti.static(self.grid.cell_volume)
        self.mass[None] += content
        ti.atomic_min(self.q_min[None], qn)
        self.n_negative[None] += ti.cast(qn < 0, ti.i64)
        return content
