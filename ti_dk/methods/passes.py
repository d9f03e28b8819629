"""The two passes of a finite-volume step over every member (paper eq. 8–10): :class:`Passes`,
the part of :class:`~.fv.SPDESolver` that makes every face flux, in rows along the last axis,
and then updates every cell from them."""

import taichi as ti

from ..core.grid import PERIODIC, across


@ti.data_oriented
class Passes:
    """The two parts of one step of ``solver`` (an :class:`~.fv.SPDESolver`, whose fields they read
    and write; its kernel ``_flux_step`` runs them): :meth:`fluxes` makes every face flux of eq. (8)
    with the solver's :class:`~.fluxes.Faces` (the noise keyed on seed, member, step and face),
    :meth:`update` applies eq. (9) (and eq. 10 for q̄)."""

    def __init__(self, solver):
        self.solver = solver

    @ti.func
    def fluxes(self, step):
        """First part of step ``step``: every face flux F of eq. (8) into the solver's ``flux``, and
        the Dirichlet inflow they carry added to its ``inflow`` (zeroed by the caller); q is not
        changed. Noise keyed on (seed, member, ``step``, face). With q̄, also the right-hand side
        of eq. (10) into its ``dqbar``, made at each cell from q̄'s fluxes through both its faces
        per axis (a scalar per cell where a field of face fluxes would take ``dim`` values, with
        the same bits)."""
        fv = self.solver
        if ti.static(fv.gaussian):
            for J in ti.grouped(fv.root):  # q̄'s square roots, once per cell
                fv.root[J] = ti.sqrt(ti.max(fv.qbar[J], fv.real(0.0)))
        for S in ti.grouped(ti.ndrange(fv.ensemble, *fv.groups[:-1], fv.spread)):  # the rows along the last axis
            if S[S.n - 1] == 0:  # a row's other iterations are empty (grid.row_spread)
                for k in range(-(-fv.groups[-1] // fv.lanes)):  # serially along the row
                    self._group_fluxes(_row_cell(S, k), step)
        G, last = ti.static(fv.group, fv.dim)
        for a in ti.static(range(fv.dim)):  # upper boundary faces (periodic ones are face 0)
            if ti.static(fv.grid.boundary[a][1] != PERIODIC):
                for K in ti.grouped(ti.ndrange(*fv.upper_layer[a])):
                    J = K
                    J[a + 1] = fv.n[a]
                    bits = fv.faces.noise(J, step, ti.math.uvec2(fv.key[0], fv.key[1]))
                    w = (J[last] % G) * fv.dim + a
                    word = bits[0]
                    for k in ti.static(range(1, 4)):
                        if w == k:
                            word = bits[k]
                    fv.flux[J][a] = fv.faces.face_flux(J, a, word)

    @ti.func
    def _group_fluxes(self, K, step):
        """:meth:`fluxes` through the lower faces of the ``L`` counter groups ``K`` (``K[last]``
        counts them along the last axis) and q̄'s right-hand side at their cells. A row is one
        iteration of the parallel loop (one per group cost a quarter of the pass)."""
        fv = self.solver
        G, last, L, n = ti.static(fv.group, fv.dim, fv.lanes, fv.n[-1])
        words = ti.Matrix.zero(ti.u32, L, 4)  # L groups of G cells along the last axis, Philox calls first
        live = ti.Vector.zero(ti.i32, L)
        for h in ti.static(range(L)):
            J = K
            J[last] = (K[last] * L + h) * G
            if J[last] < n and not self._inside_replaced(J):  # inside the replaced cells: no flux, no normal
                live[h] = 1
                bits = fv.faces.noise(J, step, ti.math.uvec2(fv.key[0], fv.key[1]))
                for w in ti.static(range(4)):
                    words[h, w] = bits[w]
        for h in ti.static(range(L)):
            if live[h]:
                I = K
                I[last] = (K[last] * L + h) * G
                for g in ti.static(range(G)):
                    if ti.static(G == 1) or I[last] < n:
                        for a in ti.static(range(fv.dim)):
                            fv.flux[I][a] = fv.faces.face_flux(I, a, words[h, g * fv.dim + a])
                    I[last] += 1
        if ti.static(fv.track_mean):
            if K[0] == 0:  # q̄'s right-hand side, both faces per axis (no face field)
                J = K
                J[last] = K[last] * L * G
                for g in ti.static(range(L * G)):
                    if J[last] < n:
                        dq = fv.real(0.0)
                        for a in ti.static(range(fv.dim)):
                            dq += (fv.faces.mean_flux(fv.upper(J, a), a) - fv.faces.mean_flux(J, a)) \
                                * fv.real(1.0 / fv.grid.dx[a])
                        fv.dqbar[J] = dq
                    J[last] += 1

    @ti.func
    def _inside_replaced(self, J):
        """Whether the ``G`` cells from ``J`` along the last axis and the cells across their lower
        faces are all replaced (:meth:`~.fv.SPDESolver.replaced_in`) (so none of those faces' fluxes is read); a boundary face
        never is. One read decides the common case, a cell not replaced."""
        fv = self.solver
        inside = False
        if ti.static(fv.replacing):
            inside = True
            K = J
            for g in ti.static(range(fv.group)):
                if inside:
                    if K[fv.dim] >= fv.n[fv.dim - 1] or fv.replaced[K] == 0:
                        inside = False
                    else:
                        for a in ti.static(range(fv.dim)):
                            L, has_left = across(fv.grid, K, a, 0)
                            if not has_left or fv.replaced[L] == 0:
                                inside = False
                K[fv.dim] += 1
        return inside

    @ti.func
    def _divergence(self, J):
        """Σ_a (F_{J+½e_a} − F_{J−½e_a}) / Δx_a: the right-hand side of eq. (9)."""
        fv = self.solver
        dq = fv.real(0.0)
        for a in ti.static(range(fv.dim)):
            dq += (fv.flux[fv.upper(J, a)][a] - fv.flux[J][a]) * fv.real(1.0 / fv.grid.dx[a])
        return dq

    @ti.func
    def update(self, diagnosing: ti.template(), n):
        r"""Second part: eq. (9), :math:`q_I \mathrel{+}= Δt \sum_a (F_{I+½e_a} - F_{I-½e_a}) / Δx_a`,
        with the fluxes of :meth:`fluxes` (and eq. 10 for q̄, in the same loop: one parallel task).
        A row along the last axis (``n`` cells) per working iteration of the
        parallel loop (the solver's ``spread`` iterations a row); with ``diagnosing``, also the sums of
        :meth:`~.fv.SPDESolver.diagnose` (zeroed by the caller) of the new q, one atomic per row.
        ``n`` is an argument, not a constant: LLVM unrolled a short constant row fully and (fast
        math) summed its last cell's divergence in another order with replaced cells than without."""
        fv = self.solver
        for S in ti.grouped(ti.ndrange(fv.ensemble, *fv.n[:-1], fv.spread)):
            if S[S.n - 1] == 0:  # a row's other iterations are empty (grid.row_spread)
                mass, q_min, negative = 0.0, fv.real(ti.math.inf), 0
                for i in range(n):
                    J = _row_cell(S, i)
                    replaced = False
                    if ti.static(fv.replacing):
                        replaced = fv.replaced[J] != 0
                    q = fv.q[J]  # `=`, not `+=`, below: on a field `+=` is an atomic add (a compare-and-swap loop)
                    fv.q[J] = ti.select(replaced, q, q + fv.real(fv.dt) * self._divergence(J))
                    if ti.static(fv.track_mean):
                        if J[0] == 0:  # q̄ has one member
                            fv.qbar[J] = fv.qbar[J] + fv.real(fv.dt) * fv.dqbar[J]  # (not atomic)
                    if ti.static(diagnosing):
                        qn = fv.q[J]
                        mass += ti.cast(qn, ti.f64)
                        q_min = ti.min(q_min, qn)
                        negative += ti.cast(qn < 0, ti.i32)
                if ti.static(diagnosing):
                    fv.mass[None] += mass * ti.static(fv.grid.cell_volume)
                    ti.atomic_min(fv.q_min[None], q_min)
                    fv.n_negative[None] += negative


@ti.func
def _row_cell(S, i):
    """The index of entry ``i`` along the last axis of the row whose other indices are ``S``'s but
    its last (the iteration within the row's spread: :func:`~..core.grid.row_spread`)."""
    return ti.Vector([S[c] for c in ti.static(range(S.n - 1))] + [i])


