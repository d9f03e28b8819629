"""The ghosts' walk into the region: the crossings of a ghost cell's lead face drawn directly
against the exact law of the clamped walk (the walked ghosts are checked in test_ghosts)."""
import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.control.registry import make_solver
from ti_dk.scene.schema import ClampWarning


@pytest.mark.parametrize("b", [0.0, 1.5, -2.0])
def test_ghosts_drawn_as_crossings_follow_the_exact_law(b):
    """Where every covered neighbour of a ghost cell lies beyond one face, the fill draws how many
    of its m ghosts cross that face, Bin(m, p), and each crossing's (start, step) from its law
    given the crossing (:meth:`Crossings.crossing`, :meth:`Crossings.entering`). Against the exact
    answers of the clamped walk from a linear in-cell profile 1 + b(u − ½), by quadrature here:
    p = ∫ ρ(v) Q(v/σ) dv (v: the distance to the face, Q the normal tail, σ = √Δt/Δx), the
    crossing's depth d = w − v beyond the face with P(D > d) ∝ ∫ ρ(v) Q((v + d)/σ) dv, the clamped
    share (ρ's mass) Q(1/σ)/p; 2·10⁵ crossings, 10⁵ counts."""
    import math

    import taichi as ti
    from ti_dk.core import rng

    with pytest.warns(ClampWarning):
        scene = load_scene("void1d", method="hybrid", regrid_interval=0, region="boxes", cells=[12, 10], ensemble=1,
                           boundary=[["dirichlet", "neumann"], "periodic"], reservoir_ppc=[[3.5, 0.0], 0.0],
                           void_lo=-1, void_hi=0.3, ppc=6.5, seed=8, C=0.5)
    s = make_solver(scene, scene.initial_ppc)
    sam, h = s.sampler.crossings, scene.grid.dx[0]
    N, M, m = 200_000, 100_000, 7
    depth, clamped, kept, counts = (np.zeros(N), np.zeros(N, np.int32), np.zeros(N, np.int32), np.zeros(M, np.int32))

    @ti.kernel
    def draw(b: ti.f64, depth: ti.types.ndarray(), clamped: ti.types.ndarray(), kept: ti.types.ndarray(),
             counts: ti.types.ndarray()):
        C = ti.Vector([5, 3])  # the slab's ghost ring (cells x ≥ 5): every covered neighbour at x = 4
        lead = s.regions.lead(0, C)
        tilt = ti.Vector([b, 0.0])
        for i in range(N):
            y, keep, cl = sam.entering(0, C, ti.u32(i), 4, 5, tilt, lead)
            depth[i], clamped[i], kept[i] = 5.0 - y[0] / h, cl, ti.cast(keep, ti.i32)
        for i in range(M):
            word = rng.philox4x32(ti.math.uvec4(ti.u32(i), 0, 0, 0), ti.math.uvec2(1, 2))[0]
            counts[i] = sam.crossing(m, lead, tilt, word)

    draw(b, depth, clamped, kept, counts)
    sigma = math.sqrt(sam.walker.dt) / h
    v = (np.arange(20_000) + 0.5) / 20_000
    rho = 1 + b * (v - 0.5)  # the profile at distance v above the face (u = v)
    Q = np.vectorize(lambda t: 0.5 * math.erfc(t / math.sqrt(2)))
    p = np.mean(rho * Q(v / sigma))
    assert kept.all()  # a slab: every crossing ends covered, and each is clamped only if it was
    z_count = (counts.mean() - m * p) / math.sqrt(m * p * (1 - p) / M)
    share = np.mean(rho) * Q(1 / sigma) / p  # the crossing's own step clamped
    along = 2 * Q(scene.grid.dx[1] / math.sqrt(sam.walker.dt))  # its step along y clamped
    z_clamp = (clamped.mean() - share - along) / math.sqrt((share * (1 - share) + along * (1 - along)) / N)
    edges = np.linspace(0, 1, 11)
    surv = np.array([np.mean(rho * Q((v + d) / sigma) * (v + d < 1)) for d in edges]) / p
    expect = -np.diff(surv) * N
    seen = np.histogram(depth, edges)[0]
    chi2 = ((seen - expect) ** 2 / expect).sum()
    assert abs(z_count) < 4 and abs(z_clamp) < 4 and chi2 < 33.7, (z_count, z_clamp, chi2)  # 9 dof: p = 1e-4
