"""FV and Gaussian schemes against the discrete Fourier theory of the linear scheme, and exact
mass conservation."""
import numpy as np
import pytest
import taichi as ti

from ti_dk import load_scene
from ti_dk.core import theory
from ti_dk.methods.fv import SPDESolver
from ti_dk.core.rng import seed_key
from ti_dk.core.grid import PERIODIC, Grid

from ..helpers import digest_on_threads, fv_mean_step


def _grid(cells, lengths=None, boundary="periodic", reservoir_ppc=0.0):
    scene = load_scene("equilibrium1d", cells=list(cells), lengths=lengths or [1.0] * len(cells),
                       boundary=boundary, reservoir_ppc=reservoir_ppc)
    return Grid.from_scene(scene)


def _count_variance(cells, lengths, ppc, C, steps, members, gaussian, real=ti.f64):
    grid = _grid(cells, lengths)
    dt = C * min(grid.dx) ** 2
    s = SPDESolver(grid, dt, members, key=seed_key(11), real=real, gaussian=gaussian)
    s.initialize(np.full(cells, float(ppc)))
    for n in range(steps):
        s.step(n)
    counts = s.density() * grid.cell_volume
    exact = theory.linear_scheme_variance(cells, tuple(dt / h**2 for h in grid.dx), ppc, steps)
    return counts.var(axis=0, ddof=1).mean(), exact


@pytest.mark.parametrize(
    "cells, lengths, members, real",
    [((100,), None, 2000, ti.f64), ((100,), None, 2000, ti.f32), ((16, 24), [1.0, 2.0], 800, ti.f64),
     ((8, 8, 8), None, 300, ti.f64)],
    ids=["1d", "1d-f32", "2d-anisotropic", "3d"],
)
def test_gaussian_variance_matches_linear_theory(cells, lengths, members, real):
    """Transient count variance after n steps from the uniform state: exact Fourier sum (1 %)."""
    var, exact = _count_variance(cells, lengths, ppc=5.0, C=0.1 if len(cells) == 1 else 0.05, steps=400,
                                 members=members, gaussian=True, real=real)
    assert abs(var / exact - 1) < 0.01, (var, exact)


def test_stationary_variance_is_above_binomial_by_the_dt_error():
    """At C = 0.1 in 1D the stationary linear-scheme variance is ~5.4 % above the binomial one."""
    exact = theory.linear_scheme_variance((100,), (0.1,), 1.0)
    assert 1.05 < exact / (1 - 1 / 100) < 1.06


def test_fv_at_100_ppc_agrees_with_linear_theory():
    var, exact = _count_variance((100,), None, ppc=100.0, C=0.1, steps=400, members=1000, gaussian=False)
    assert abs(var / exact - 1) < 0.03, (var, exact)


@pytest.mark.parametrize("cells, boundary", [((50,), "periodic"), ((50,), "neumann"), ((12, 10), "neumann"),
                                             ((6, 5, 4), ["periodic", "neumann", "periodic"])])
@pytest.mark.parametrize("gaussian", [False, True], ids=["fv", "gaussian"])
def test_mass_conserved_to_roundoff(cells, boundary, gaussian):
    grid = _grid(cells, boundary=boundary)
    s = SPDESolver(grid, 0.1 * min(grid.dx) ** 2, 4, key=seed_key(3), real=ti.f64, gaussian=gaussian)
    ppc = np.random.default_rng(0).uniform(0.0, 3.0, size=cells)  # low densities: negative cells occur
    s.initialize(ppc)
    total0 = ppc.sum() * 4
    masses = []
    for n in range(200):
        s.step(n)
        masses.append(s.diagnostics()["mass"])
    assert np.max(np.abs(np.array(masses) / total0 - 1)) < 1e-12
    assert s.diagnostics()["negative_cells"] > 0  # a non-trivial test: noise is strong here


def test_dirichlet_balance_equals_boundary_fluxes():
    grid = _grid((40,), boundary=[["dirichlet", "neumann"]], reservoir_ppc=[[8.0, 0.0]])
    s = SPDESolver(grid, 0.1 * grid.dx[0] ** 2, 8, key=seed_key(5), real=ti.f64)
    s.initialize(np.full(40, 2.0))
    mass, inflow = [2.0 * 40 * 8], []
    for n in range(300):
        s.step(n)
        d = s.diagnostics()
        mass.append(d["mass"])
        inflow.append(d["boundary_inflow"])
    assert np.allclose(np.diff(mass), inflow, rtol=0, atol=1e-9 * mass[0])
    assert mass[-1] > mass[0] + 100  # the reservoir really fed the domain


def test_noise_depends_on_seed_and_member():
    grid = _grid((30,))
    out = []
    for seed in (1, 1, 2):
        s = SPDESolver(grid, 0.1 * grid.dx[0] ** 2, 2, key=seed_key(seed), real=ti.f64)
        s.initialize(np.full(30, 10.0))
        s.step(0)
        out.append(s.density())
    assert np.array_equal(out[0], out[1])
    assert not np.array_equal(out[0], out[2])
    assert not np.array_equal(out[0][0], out[0][1])


_BITS = """
import hashlib, sys
import numpy as np
import ti_dk, taichi as ti
from ti_dk.methods.fv import SPDESolver
from ti_dk.core.rng import seed_key
from ti_dk.core.grid import PERIODIC, Grid
ti_dk.init("cpu", int(sys.argv[1]))
h = hashlib.sha256()
for cells, E, real in (((100,), 64, ti.f64), ((40, 30), 2, ti.f32), ((10, 9, 8), 2, ti.f64)):
    grid = Grid(cells, (1.0,) * len(cells), ((2, 2),) + ((0, 0),) * (len(cells) - 1),
                ((7.0, 1.0),) + ((0.0, 0.0),) * (len(cells) - 1))
    s = SPDESolver(grid, 0.1 * min(grid.dx) ** 2, E, key=seed_key((1 << 40) + 9), real=real)
    s.initialize(np.full(cells, 3.0))
    for n in range(30):
        s.step(n)
    h.update(s.q.to_numpy().tobytes())
print(h.hexdigest())
"""


def test_same_seed_same_bits_on_one_and_two_threads():
    """The noise is counter-based: the state after 30 steps is bit-identical whatever the thread count."""
    one, two = digest_on_threads(_BITS)
    assert one == two


@pytest.mark.parametrize("boundary", ["periodic", [["dirichlet", "neumann"]], [["neumann", "dirichlet"]]])
def test_fused_1d_step_equals_the_three_kernel_step(boundary):
    """The per-member 1D step and the hybrid's step (``advance``, then ``diagnose``) give the same bits,
    except next to an upper Dirichlet face: there the fused kernel sees the reservoir density as a
    constant and LLVM's fast-math folds ``(ρ − q)/2Δx`` differently (measured: 1 ulp in the last
    cell, now and then), so those cells are held to 4 ulp."""
    grid = _grid((37,), boundary=boundary, reservoir_ppc=[[3.0, 5.0]] if boundary != "periodic" else 0.0)
    a, b = (SPDESolver(grid, 0.1 * grid.dx[0] ** 2, 5, key=seed_key(4), real=ti.f64) for _ in range(2))
    ppc = np.random.default_rng(1).uniform(0.0, 4.0, size=37)
    a.initialize(ppc)
    b.initialize(ppc)
    for n in range(20):
        b.q.from_numpy(a.q.to_numpy())  # one step from the same state (a 1-ulp difference would grow)
        a.step(n)
        b.advance(n)
        b.diagnose()
        qa, qb = a.q.to_numpy(), b.q.to_numpy()
        if boundary == [["neumann", "dirichlet"]]:
            np.testing.assert_array_max_ulp(qa[:, -1], qb[:, -1], maxulp=4)
            qa, qb = qa[:, :-1], qb[:, :-1]
        assert np.array_equal(qa, qb)
        da, db = a.diagnostics(), b.diagnostics()
        assert da["negative_cells"] == db["negative_cells"] and da["min_density"] == db["min_density"]
        assert da["mass"] == pytest.approx(db["mass"], rel=1e-13)
        assert da["boundary_inflow"] == pytest.approx(db["boundary_inflow"], rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("cells, boundary", [
    ((30,), [["dirichlet", "neumann"]]),
    ((9, 8), [["neumann", "dirichlet"], ["periodic", "periodic"]]),
    ((5, 6, 7), [["dirichlet", "dirichlet"], ["neumann", "neumann"], ["periodic", "periodic"]]),
])
def test_mean_density_follows_the_discrete_heat_equation(cells, boundary):
    """q̄ (eq. 10, advanced beside q for the hybrid's ghosts and the Gaussian scheme's amplitude)
    against the same scheme written face by face in NumPy, every boundary kind on some axis."""
    reservoir = [[2.0, 3.0]] * len(cells)
    grid = _grid(cells, boundary=boundary, reservoir_ppc=reservoir)
    dt = 0.2 * min(grid.dx) ** 2
    s = SPDESolver(grid, dt, 2, key=seed_key(3), real=ti.f64, track_mean=True)
    ppc = np.random.default_rng(2).uniform(0.0, 8.0, size=cells)
    s.initialize(ppc)
    q = ppc / grid.cell_volume
    for n in range(6):
        s.advance(n)
        q = fv_mean_step(q, grid.dx, dt, [tuple(b) for b in boundary], grid.reservoir)
    np.testing.assert_allclose(s.qbar.to_numpy()[0], q, rtol=1e-12, atol=0)


@pytest.mark.parametrize("cells, boundary", [
    ((41,), "periodic"),  # groups of G = 4 cells, the last one partial
    ((12, 9), [["dirichlet", "neumann"], ["periodic", "periodic"]]),  # G = 2, a partial group per row
    ((6, 5, 7), [["periodic", "periodic"], ["neumann", "dirichlet"], ["dirichlet", "dirichlet"]]),
])
def test_replaced_cells_change_no_other_cell_or_face(cells, boundary):
    """With :meth:`SPDESolver.replaced_in` (the hybrid's covered cells) a step leaves the replaced
    cells as they were and skips fluxes between two of them, and every other cell and face and the
    Dirichlet inflow keep the bits of the step without it (each step starts from the same q)."""
    reservoir = [[2.0, 3.0]] * len(cells)
    grid = _grid(cells, boundary=boundary, reservoir_ppc=reservoir)
    dt = 0.1 * min(grid.dx) ** 2
    E, d = 3, len(cells)
    a, b = (SPDESolver(grid, dt, E, key=seed_key(5), real=ti.f64, track_mean=True) for _ in range(2))
    rng = np.random.default_rng(7)
    mask = rng.random((E, *cells)) < 0.6  # members differ; blobs and single cells both occur
    field = ti.field(ti.u8, shape=mask.shape)
    field.from_numpy(mask.astype(np.uint8))
    b.replaced_in(field)
    ppc = rng.uniform(1.0, 9.0, size=cells)
    a.initialize(ppc)
    b.initialize(ppc)
    # the faces a step may skip: lower face of J along axis k with J and the cell across it replaced
    skip = []
    for k in range(d):
        across_ = np.roll(mask, 1, axis=k + 1)
        if grid.boundary[k][0] != PERIODIC:
            np.moveaxis(across_, k + 1, 0)[0] = False  # beyond a wall: a boundary face is always made
        skip.append(mask & across_)
    assert all(s.any() for s in skip) and not all(s.all() for s in skip)
    for n in range(4):
        q0 = a.q.to_numpy()
        b.q.from_numpy(q0)
        b.flux.from_numpy(np.full(b.flux.shape + (d,), np.nan))
        a.advance(n)
        b.advance(n)
        qa, qb = a.q.to_numpy(), b.q.to_numpy()
        assert np.array_equal(qa[~mask], qb[~mask]) and np.array_equal(qb[mask], q0[mask])
        fa, fb = a.flux.to_numpy(), b.flux.to_numpy()
        skipped = 0
        for k in range(d):
            inner = (slice(None),) + tuple(slice(0, m) for m in cells)  # lower faces of the cells
            Fa, Fb = fa[inner + (k,)], fb[inner + (k,)]
            assert np.array_equal(Fa[~skip[k]], Fb[~skip[k]])  # every face a step reads
            made = ~np.isnan(Fb[skip[k]])  # the kernel skips whole groups of faces (G cells)
            assert np.array_equal(Fa[skip[k]][made], Fb[skip[k]][made])
            skipped += (~made).sum()
            if grid.boundary[k][1] != PERIODIC:  # the upper boundary faces
                upper = inner[:k + 1] + (cells[k],) + inner[k + 2:] + (k,)
                assert np.array_equal(fa[upper], fb[upper])
        assert skipped > 0
        assert a.inflow[None] == b.inflow[None]
        # q̄ (no noise, every cell) to a few ulp: fast math may fold its sums differently in the two kernels
        np.testing.assert_array_max_ulp(a.qbar.to_numpy(), b.qbar.to_numpy(), maxulp=4)
