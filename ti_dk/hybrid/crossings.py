"""The hybrid's ghosts walking into the particle region (paper §3, step 3): how many of a ghost
cell's ghosts end their walk in the region, and where each one lands."""

import math

import taichi as ti

from ..core import rng
from ..core.grid import NEUMANN, PERIODIC, cell_of, offset
from ..methods.particles import Walker
from .region import Region


def _reach(sigma: float) -> tuple[float, float, float]:
    """``(σ, E[w], E[w²])`` of ``w = min(σZ, 1)⁺`` (Z standard normal; σ = √Δt/Δx): the distance in
    cells a clamped step carries a particle towards a face, 0 if it moves away. A particle a
    distance ``v`` (in cells) from the face crosses it iff ``w > v``."""
    a = 1.0 / sigma
    phi0, phia = 1.0 / math.sqrt(2 * math.pi), math.exp(-0.5 * a * a) / math.sqrt(2 * math.pi)
    tail = 0.5 * math.erfc(a / math.sqrt(2))  # P(Z > 1/σ): the clamped steps
    return sigma, sigma * (phi0 - phia) + tail, sigma**2 * (0.5 - tail - a * phia) + tail


@ti.data_oriented
class Crossings:
    """The walk of a ghost cell's ghosts into the region (ti.funcs for :class:`ghosts.Sampler`).

    A ghost enters only if its clamped step (at most one cell per axis) ends in a covered cell: at
    an offset ``δ ∈ {−1, 0, 1}^d`` that its cell's :meth:`Region.near` sets. Its axes move
    independently (the in-cell profile is a product over the axes, and so is the step), so it ends at
    ``δ`` with probability ``∏_a p_a(δ_a)`` (:meth:`_axes`). Without a potential the entrants are
    drawn directly: how many of the cell's ghosts enter (:meth:`count`), then each one's offset and,
    axis by axis, its position given that offset (:meth:`entrant`); the ghosts that do not enter
    are never made. With a potential (the drift depends on the position) each ghost is walked
    (:meth:`walk`).
    """

    def __init__(self, grid, region: Region, walker: Walker, key):
        self.grid, self.region, self.walker, self.key = grid, region, walker, key
        self.dim, self.n, self.real = grid.dim, tuple(grid.cells), walker.real
        self.direct = not walker.drifting  # entrants drawn directly (compile-time)
        self.reach = [_reach(math.sqrt(walker.dt) / h) for h in grid.dx]  # (σ, E w, E w²) per axis
        d = self.dim
        # per axis, the offsets (Region.near's bits) one step below the cell along it, and above it
        self.below = [sum(1 << o for o in range(3**d) if (o // 3**a) % 3 == 0) for a in range(d)]
        self.above = [sum(1 << o for o in range(3**d) if (o // 3**a) % 3 == 2) for a in range(d)]

    @ti.func
    def lead(self, near):
        """``2a + s`` for the first axis ``a`` such that every covered offset of ``near`` (:meth:`Region.near`)
        lies one step below the cell along it (``s = 0``) or every one above (``s = 1``): a walk
        step that ends covered crosses that face. −1 where no axis is such (a ring cell in a concave
        corner of the region)."""
        out = -1
        for b in ti.static(range(self.dim)):
            a = ti.static(self.dim - 1 - b)  # the last assignment wins: the first axis
            if near != 0 and near & ti.u32(~self.below[a] & 0xFFFFFFFF) == 0:
                out = 2 * a
            elif near != 0 and near & ti.u32(~self.above[a] & 0xFFFFFFFF) == 0:
                out = 2 * a + 1
        return out

    @ti.func
    def walk(self, e, C, id0, y, step, birth, lead):
        """Ghost ``id0`` of cell ``C`` at ``y`` walked one sub-step (:meth:`Walker.axis_step` per
        axis, the steps and numbers of :meth:`Walker.move`): its end point, whether that is
        covered, its clamped steps (counted for the kept ghosts only). Along the ``lead`` face's
        axis first: a ghost that does not cross it cannot end covered and is dropped without the
        other axes' normals, moves and the region lookup (most are: about one in ten enters)."""
        keep, clamped = True, 0
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
        if not keep:
            clamped = 0
        return z, keep, clamped

    @ti.func
    def _face(self, a: ti.template(), side, tilt):
        """For face ``side`` (0: lower, 1: upper) of axis ``a`` and the cell's profile ``tilt``
        (:meth:`InCell.tilt`): ``(σ, E w, E w², c0, c1)``, the axis's :func:`_reach` and the
        profile's density at distance ``v`` (cells) from the face, ``c0 + c1 v``
        (:meth:`Walker.in_cell`: ``1 + b (u − ½)``)."""
        # (a plain assignment: `sig, ... = ti.static(...)` would bind new names, not assign these)
        sig, ew, ew2 = [ti.f64(ti.static(self.reach[a][i])) for i in ti.static(range(3))]
        b = ti.cast(tilt[a], ti.f64)
        c0, c1 = 1.0 - 0.5 * b, b  # the low face: v = u
        if side:  # the high face: v = 1 − u
            c0, c1 = 1.0 + 0.5 * b, -b
        return sig, ew, ew2, c0, c1

    @ti.func
    def _axes(self, C, tilt):
        r"""Per axis ``a``, the probabilities that a ghost of cell ``C`` ends one cell below it, in it, or
        one cell above it: ``p = ∫∫ (c0 + c1 v) φ(z) 1[w(z) > v] dv dz = c0 E w + c1 E w² / 2`` for
        each face (:meth:`_face`); a step through a Neumann wall is reflected back into the cell, one
        through a Dirichlet wall leaves the domain (never covered)."""
        lo = ti.Vector.zero(ti.f64, self.dim)
        hi = ti.Vector.zero(ti.f64, self.dim)
        stay = ti.Vector.zero(ti.f64, self.dim)
        for a in ti.static(range(self.dim)):
            for side in ti.static(range(2)):
                _sig, ew, ew2, c0, c1 = self._face(a, side, tilt)
                p = ti.min(ti.max(c0 * ew + 0.5 * c1 * ew2, 0.0), 1.0 - 1e-12)
                if ti.static(side == 0):
                    lo[a] = p
                else:
                    hi[a] = p
            stay[a] = 1.0 - lo[a] - hi[a]
            if ti.static(self.grid.boundary[a][0] == NEUMANN):
                if C[a] == 0:
                    stay[a] += lo[a]
            if ti.static(self.grid.boundary[a][1] == NEUMANN):
                if C[a] == self.n[a] - 1:
                    stay[a] += hi[a]
        return lo, stay, hi

    @ti.func
    def _weight(self, o, lo, stay, hi):
        """The probability ``∏_a p_a(δ_a)`` of ending at offset ``o`` (:func:`~ti_dk.core.grid.offset`)."""
        w, off = 1.0, offset(o, self.dim)
        for a in ti.static(range(self.dim)):
            w *= ti.select(off[a] < 0, lo[a], ti.select(off[a] == 0, stay[a], hi[a]))
        return w

    @ti.func
    def _running(self, near, lo, stay, hi):
        """The running sum of :meth:`_weight` over the covered offsets ``near`` in ascending order: entry
        ``o`` holds it up to and including offset ``o`` (the last entry: the total). Made once a ghost
        cell, so that each entrant finds its offset by compares alone (:meth:`_pick`): made again for
        every entrant, the weights made the 3D fill 12 % slower (sphere3d 64³, 300 per cell)."""
        run = ti.Vector.zero(ti.f64, 3**self.dim)
        total = 0.0
        for o in ti.static(range(3**self.dim)):  # unrolled: the vector's entries are registers
            if (near >> ti.u32(o)) & ti.u32(1):
                total += self._weight(o, lo, stay, hi)
            run[o] = total
        return run

    @ti.func
    def _pick(self, near, run, target):
        """The first covered offset at which :meth:`_running`'s sum ``run`` passes ``target`` (the last
        covered one where none does: rounding)."""
        chosen, last = -1, 0
        for o in ti.static(range(3**self.dim)):
            if (near >> ti.u32(o)) & ti.u32(1):
                if chosen < 0 and target < run[o]:
                    chosen = o
                last = o
        if chosen < 0:
            chosen = last
        return chosen

    @ti.func
    def count(self, m, near, C, tilt, word):
        """How many of cell ``C``'s ``m`` ghosts end their walk covered: ``Bin(m, P)`` (each on its own),
        ``P`` the sum of :meth:`_weight` over the covered offsets ``near``, drawn by inversion of one
        uniform ``word``; with :meth:`_running`'s sums for :meth:`entrant`."""
        lo, stay, hi = self._axes(C, tilt)
        run = self._running(near, lo, stay, hi)
        p = ti.min(run[3**self.dim - 1], 1.0 - 1e-12)
        u = rng.uniform(word, ti.f64)
        P = ti.pow(1.0 - p, ti.cast(m, ti.f64))
        F, k = P, 0
        while u > F and k < m:
            P *= ti.cast(m - k, ti.f64) / ti.cast(k + 1, ti.f64) * p / (1.0 - p)
            k += 1
            F += P
        return k, run

    @ti.func
    def _words(self, e, id0, step, t):
        """Philox words for entrant ``id0``: counters ``(id, step, member, SAMPLE_ENTRY + t)``."""
        return rng.philox4x32(ti.math.uvec4(id0, ti.u32(step), self.walker.member(e),
                                            ti.u32(rng.SAMPLE_ENTRY) | (ti.u32(t) << rng.PURPOSE_BITS)),
                              ti.math.uvec2(self.key[0], self.key[1]))

    @ti.func
    def entrant(self, e, C, id0, step, near, tilt, run):
        r"""Entrant ``id0`` (identity) of cell ``C`` (one of :meth:`count`'s): its position after its walk
        and its clamped steps. Its offset is drawn among the covered ones ``near`` with
        probabilities ∝ :meth:`_weight` (``run``: their running sums, :meth:`_running`), then each axis given its part of the
        offset: across a face by :meth:`_cross`, within the cell by :meth:`_stay`. Axis ``a`` uses
        counters ``(id, step, member, SAMPLE_ENTRY + t)``, ``t`` from ``1024 a``; the offset the fourth
        word of ``t = 0``."""
        chosen = self._pick(near, run, rng.uniform(self._words(e, id0, step, 0)[3], ti.f64) * run[3**self.dim - 1])
        off = offset(chosen, self.dim)
        y = ti.Vector.zero(self.real, self.dim)
        clamped = 0
        for a in ti.static(range(self.dim)):
            ya, c = self.real(0.0), 0
            if off[a] == 0:
                ya, c = self._stay(e, C, id0, step, a, tilt)
            else:
                ya, c = self._cross(e, C, id0, step, a, ti.cast(off[a] > 0, ti.i32), tilt)
            y[a] = ya
            clamped += c
        return y, clamped

    @ti.func
    def _cross(self, e, C, id0, step, a: ti.template(), side, tilt):
        r"""Axis ``a`` of an entrant of cell ``C`` that crosses face ``side``: its coordinate after the
        step, and 1 if the step was clamped. The pair (distance ``v`` to the face, step ``w``) is drawn
        from its law given a crossing, ``∝ (c0 + c1 v) φ(z) 1[v < w(z)]``: ``z`` from the Rayleigh
        density ``z φ(z)`` (``√(−2 ln U)``) kept with probability ``min(1, 1/(σz)) (c0 + c1 w/2) /
        (c0 + max(c1, 0)/2)`` (the clamp, and the profile's mass below ``w``), then ``v`` from
        ``c0 + c1 v`` on ``(0, w)`` by inversion."""
        sig, _ew, _ew2, c0, c1 = self._face(a, side, tilt)
        top = c0 + 0.5 * ti.max(c1, 0.0)
        w, v, t, done = 0.0, 0.0, 0, False
        while not done and t < 1000:
            r = self._words(e, id0, step, 1024 * a + t)
            z = ti.sqrt(-2.0 * ti.log(rng.uniform(r[0], ti.f64)))
            w = ti.min(sig * z, 1.0)
            done = rng.uniform(r[1], ti.f64) * top * ti.max(sig * z, 1.0) < c0 + 0.5 * c1 * w
            R = rng.uniform(r[2], ti.f64) * (c0 * w + 0.5 * c1 * w * w)
            v = 2.0 * R / (c0 + ti.sqrt(ti.max(c0 * c0 + 2.0 * c1 * R, 0.0)))
            t += 1
        h, L = ti.static(self.grid.dx[a], self.grid.lengths[a])
        x = (ti.cast(C[a], ti.f64) + v - w) * h  # the low face: from v above it to w − v below
        if side:
            x = (ti.cast(C[a], ti.f64) + 1.0 - v + w) * h
        if ti.static(self.grid.boundary[a][0] == PERIODIC):
            if x < 0:
                x += L
            elif x >= L:
                x -= L
        return self.real(x), ti.cast(w >= 1.0, ti.i32)

    @ti.func
    def _stay(self, e, C, id0, step, a: ti.template(), tilt):
        """Axis ``a`` of an entrant of cell ``C`` whose step ends in its own cell along it (a Neumann
        wall's reflection included): a position from the profile and a step of the walk
        (:meth:`Walker.axis_step`), drawn again until they end so; its coordinate, and 1 if the step
        was clamped."""
        h = ti.static(self.grid.dx[a])
        ya, clamped, t, done = self.real(0.0), 0, 0, False
        while not done and t < 1000:
            r = self._words(e, id0, step, 1024 * a + t)
            x = (self.real(C[a]) + self.walker.in_cell_axis(r[0], tilt[a])) * self.real(h)
            z, alive, c, _raw = self.walker.axis_step(x, a, r[1], self.real(0.0))
            done = alive and cell_of(z, self.real(h), self.n[a]) == C[a]
            ya, clamped = z, c
            t += 1
        return ya, clamped
