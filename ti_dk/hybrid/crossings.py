"""The hybrid's ghosts walking into the particle region (paper §3, step 3): which face of a ghost
cell leads into the region, how many of its ghosts cross that face, and where each one lands."""

import math

import taichi as ti

from ..core import rng
from ..core.grid import PERIODIC, cell_of
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

    A ghost enters only if its clamped step (at most one cell per axis) ends in a covered cell.
    Where every covered neighbour of its cell lies beyond one face (:meth:`Region.lead`; nearly
    every ghost cell), it must cross that face: without a potential the crossings are drawn directly
    (:meth:`crossing`, :meth:`entering`, the law of the ghosts that cross); with one (the drift
    depends on the position) or without a lead face each ghost is walked (:meth:`walk`).
    """

    def __init__(self, grid, region: Region, walker: Walker, key):
        self.grid, self.region, self.walker, self.key = grid, region, walker, key
        self.dim, self.n, self.real = grid.dim, tuple(grid.cells), walker.real
        self.direct = not walker.drifting  # crossings drawn directly (compile-time)
        self.reach = [_reach(math.sqrt(walker.dt) / h) for h in grid.dx]  # (σ, E w, E w²) per axis

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
    def _lead_profile(self, lead, tilt):
        """For the lead face ``lead`` (:meth:`Region.lead`) and the cell's profile ``tilt`` (:meth:`tilt`):
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
    def entering(self, e, C, id0, step, birth, tilt, lead):
        r"""Ghost ``id0`` (identity) of the :meth:`crossing` ones of cell ``C``: its position after its
        walk, whether that is covered and its clamped steps (as :meth:`walk`).

        Along the lead axis the pair (distance ``v`` to the face, step ``w``) is drawn from its law
        given a crossing, ``∝ (c0 + c1 v) φ(z) 1[v < w(z)]``: ``z`` from the Rayleigh density
        ``z φ(z)`` (``√(−2 ln U)``) kept with probability ``min(1, 1/(σz)) (c0 + c1 w/2) / (c0 +
        max(c1, 0)/2)`` (the clamp, and the profile's mass below ``w``), then ``v`` from ``c0 + c1 v``
        on ``(0, w)`` by inversion; counters ``(id, step, member, SAMPLE_ENTRY + attempt)``. The
        other axes are those of a ghost of :meth:`ghosts.Sampler._placed` (position words, then the walk's), drawn
        without condition: a crossing ends covered or not by them (every covered neighbour lies
        beyond the lead face)."""
        key = ti.math.uvec2(self.key[0], self.key[1])
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
        return y, keep, clamped

