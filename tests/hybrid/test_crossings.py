"""The ghosts' walk into the region: the entrants of a ghost cell drawn directly (how many, at which
covered offset, where) against the exact law of the clamped walk by quadrature (the walked ghosts
are checked in test_ghosts)."""
import math

import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.control.registry import make_solver
from ti_dk.scene.schema import ClampWarning

N, M, m = 200_000, 100_000, 7  # entrants drawn, counts drawn, ghosts in the cell
_U = (np.arange(20_000) + 0.5) / 20_000  # quadrature points in a cell


def _Q(t):
    """The normal tail P(Z > t)."""
    return 0.5 * np.vectorize(math.erfc)(np.asarray(t) / math.sqrt(2))


def _axis(b, sigma):
    """One axis of the clamped walk from the in-cell profile 1 + b(u − ½): the probabilities of ending
    one cell below, in the cell (no wall), one cell above."""
    rho = 1 + b * (_U - 0.5)
    lo, hi = np.mean(rho * _Q(_U / sigma)), np.mean(rho * _Q((1 - _U) / sigma))
    return lo, 1 - lo - hi, hi


@pytest.fixture(scope="module")
def drawn():
    """A 12 × 10 grid, x from a Dirichlet side to a Neumann one, y periodic, C = 0.5 (σ ≈ 0.7 a cell:
    clamped steps are common, as this test wants). ``draw(C, covered, tilt)`` runs
    :meth:`Crossings.count` M times and :meth:`Crossings.entrant` N times for ghost cell ``C`` of a
    region covering ``covered``: the counts, the entrants' end points (in cells) and clamped axes."""
    import taichi as ti
    from ti_dk.core import rng

    with pytest.warns(ClampWarning):
        scene = load_scene("void1d", method="hybrid", regrid_interval=0, cells=[12, 10], ensemble=1,
                           boundary=[["dirichlet", "neumann"], "periodic"], reservoir_ppc=[[3.5, 0.0], 0.0],
                           void_lo=-1, void_hi=0.3, ppc=6.5, seed=8, C=0.5)
    s = make_solver(scene, scene.initial_ppc)
    cr, (hx, hy) = s.sampler.crossings, scene.grid.dx

    @ti.kernel
    def run(c0: ti.i32, c1: ti.i32, b0: ti.f64, b1: ti.f64, y: ti.types.ndarray(), clamped: ti.types.ndarray(),
            counts: ti.types.ndarray()):
        C, tilt = ti.Vector([c0, c1]), ti.Vector([b0, b1])
        near = s.regions.near(0, C)
        for i in range(N):
            _n, run = cr.count(m, near, C, tilt, ti.u32(0))
            z, cl = cr.entrant(0, C, ti.u32(i), 4, near, tilt, run)
            y[i, 0], y[i, 1], clamped[i] = z[0] / hx, z[1] / hy, cl
        for i in range(M):
            word = rng.philox4x32(ti.math.uvec4(ti.u32(i), 0, 0, 0), ti.math.uvec2(1, 2))[0]
            counts[i] = cr.count(m, near, C, tilt, word)[0]

    def draw(C, covered, tilt):
        mask = np.zeros((1, 12, 10), dtype=np.uint8)
        for c in covered:
            mask[(0, *c)] = 1
        s.regions.load_state({"covered": mask, "boxes": np.zeros((0, 5), dtype=np.int64)})
        y, clamped, counts = np.zeros((N, 2)), np.zeros(N, np.int32), np.zeros(M, np.int32)
        run(*C, *tilt, y, clamped, counts)
        return y, clamped, counts

    draw.sigma = [math.sqrt(cr.walker.dt) / h for h in (hx, hy)]
    return draw


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (1.5, -1.0), (-2.0, 2.0)])
def test_entrants_of_a_concave_corner_follow_the_exact_law(drawn, tilt):
    """A ghost cell in a concave corner of the region (covered neighbours below it along x, above it
    along y, and the diagonal between): the entrants' number, Bin(m, P) with P = Σ ∏_a p_a(δ_a) over
    the covered offsets; their offsets' shares ∝ ∏_a p_a(δ_a); the depth beyond the x face of those
    that cross it and the end point along y of those that stay in their row; their clamped axes."""
    C, offsets = (5, 3), [(-1, 0), (-1, 1), (0, 1)]
    y, clamped, counts = drawn(C, [(C[0] + a, C[1] + b) for a, b in offsets], tilt)
    sig = drawn.sigma
    p = [dict(zip((-1, 0, 1), _axis(b, s))) for b, s in zip(tilt, sig)]
    w = np.array([p[0][a] * p[1][b] for a, b in offsets])
    P = w.sum()
    z_count = (counts.mean() - m * P) / math.sqrt(m * P * (1 - P) / M)
    end = np.floor(y).astype(int) - np.array(C)
    seen = np.array([np.sum((end[:, 0] == a) & (end[:, 1] == b)) for a, b in offsets])
    assert seen.sum() == N  # every entrant ends covered
    chi2_offsets = ((seen - N * w / P) ** 2 / (N * w / P)).sum()  # 2 dof
    # along x, the crossings of the low face: the depth d = w − v beyond it, P(D > d) ∝ ∫ ρ(v) Q((v + d)/σ) dv
    rho_x = 1 + tilt[0] * (_U - 0.5)
    edges = np.linspace(0, 1, 11)
    surv = np.array([np.mean(rho_x * _Q((_U + d) / sig[0]) * (_U + d < 1)) for d in edges]) / p[0][-1]
    depth = C[0] - y[end[:, 0] == -1, 0]
    chi2_depth = ((np.histogram(depth, edges)[0] - (e := -np.diff(surv) * depth.size)) ** 2 / e).sum()
    # along y, those that stay in their row: the end point e ∈ [0, 1) has density ∝ ∫ ρ(u) φ((e − u)/σ) du
    rho_y = 1 + tilt[1] * (_U - 0.5)
    cdf = np.array([np.mean(rho_y * (1 - _Q((e - _U) / sig[1]) - _Q(_U / sig[1]))) for e in edges]) / p[1][0]
    stay = y[end[:, 1] == 0, 1] - C[1]
    chi2_stay = ((np.histogram(stay, edges)[0] - (e := np.diff(cdf) * stay.size)) ** 2 / e).sum()
    # clamped: a crossing's own step with probability Q(1/σ)/p (the profile's mass is 1); a step that stays, never
    share = sum(wi / P * sum(_Q(1 / s) / pa[d] for d, s, pa in zip(o, sig, p) if d) for wi, o in zip(w, offsets))
    z_clamp = (clamped.mean() - share) / math.sqrt(clamped.var() / N)
    assert abs(z_count) < 4 and abs(z_clamp) < 4, (z_count, z_clamp)
    assert chi2_offsets < 18.4 and chi2_depth < 33.7 and chi2_stay < 33.7, (chi2_offsets, chi2_depth, chi2_stay)  # p = 1e-4


def test_a_step_through_a_neumann_wall_stays_in_its_cell(drawn):
    """A ghost cell at the Neumann wall (x = 11 of 12) whose only covered neighbour is above it along
    y: a step through the wall is reflected back into the cell, so P = (1 − p_below,x) p_above,y."""
    C = (11, 3)
    y, _clamped, counts = drawn(C, [(11, 4)], (0.5, 0.0))
    lo_x, _, _ = _axis(0.5, drawn.sigma[0])
    P = (1 - lo_x) * _axis(0.0, drawn.sigma[1])[2]
    z_count = (counts.mean() - m * P) / math.sqrt(m * P * (1 - P) / M)
    assert abs(z_count) < 4, z_count
    assert np.all(np.minimum(np.floor(y).astype(int), (11, 9)) == (11, 4))
