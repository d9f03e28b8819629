"""Grid geometry against hand-computed values, cell_of at and around every face, and the face rule (across)."""
import numpy as np
import pytest
import taichi as ti

from ti_dk import load_scene
from ti_dk.core.grid import (DIRICHLET, INTERIOR, NEUMANN, PERIODIC, SCAN_BLOCK, Grid, across, block_scan, cell_of,
                            exclusive_scan, face_kind, numpy_dtype, row_spread, spread)


def test_geometry_of_an_anisotropic_2d_grid():
    scene = load_scene("ellipse2d", cells=[4, 5], lengths=[2.0, 1.0], boundary=[["dirichlet", "neumann"], "periodic"],
                       reservoir_ppc=[[6.0, 0.0], 0.0], method="fv", compare="none", t_end=0.01)
    g = Grid.from_scene(scene)
    assert g.dim == 2 and g.dx == pytest.approx((0.5, 0.2))
    assert g.cell_volume == pytest.approx(0.1)
    assert g.face_area == pytest.approx((0.2, 0.5))  # a face normal to x is dy long, one normal to y dx
    assert g.boundary == ((DIRICHLET, NEUMANN), (PERIODIC, PERIODIC))
    assert np.allclose(g.reservoir, ((60.0, 0.0), (0.0, 0.0)))  # 6 particles per cell / 0.1 volume
    assert g.reservoir_ppc_max == pytest.approx(6.0) and g.has_dirichlet


def test_geometry_in_1d_and_3d():
    g1 = Grid.from_scene(load_scene("void1d", cells=[40], lengths=[2.0]))
    assert g1.dim == 1 and g1.cell_volume == pytest.approx(0.05) and g1.face_area == pytest.approx((1.0,))
    assert not g1.has_dirichlet and g1.reservoir_ppc_max == 0
    g3 = Grid.from_scene(load_scene("sphere3d", cells=[2, 4, 8], lengths=[1.0, 2.0, 4.0], method="fv", compare="none",
                                    t_end=0.1))
    assert g3.dx == pytest.approx((0.5, 0.5, 0.5)) and g3.cell_volume == pytest.approx(0.125)
    assert g3.face_area == pytest.approx((0.25, 0.25, 0.25))
    assert np.prod(g3.cells) * g3.cell_volume == pytest.approx(np.prod(g3.lengths))


def test_numpy_dtype():
    assert numpy_dtype(ti.f32) is np.float32 and numpy_dtype(ti.f64) is np.float64


@ti.kernel
def _cells_of(x: ti.types.ndarray(), out: ti.types.ndarray(), h: ti.f64, n: ti.i32):
    for i in x:
        out[i] = cell_of(x[i], h, n)


def test_cell_of_at_faces_and_outside():
    n, h = 8, 0.125  # h exact in binary: x = k h is exactly on face k
    faces = np.arange(n + 1) * h
    x = np.concatenate([faces, np.nextafter(faces, -np.inf), faces + h / 2, [-0.3, -1e-300, 1.0 + 1e-9, 7.0]])
    out = np.zeros(x.size, dtype=np.int32)
    _cells_of(x, out, h, n)
    k = np.arange(n + 1)
    want = np.concatenate([np.minimum(k, n - 1),  # a face belongs to the cell above it; x = L to the last cell
                           np.clip(k - 1, 0, n - 1),  # just below a face: the cell below (clamped at 0)
                           np.minimum(k, n - 1),  # cell centres
                           [0, 0, n - 1, n - 1]])  # outside: clamped into [0, n)
    assert out.tolist() == want.tolist()


@ti.data_oriented
class _Faces:
    def __init__(self, grid):
        self.grid = grid

    @ti.kernel
    def across(self, J: ti.types.ndarray(), a: ti.template(), side: ti.template(), out: ti.types.ndarray()):
        for i in range(J.shape[0]):
            K, inside = across(self.grid, ti.Vector([J[i, 0], J[i, 1], J[i, 2]]), a, side)
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = K[0], K[1], K[2], ti.cast(inside, ti.i32)

    @ti.kernel
    def kinds(self, a: ti.template(), out: ti.types.ndarray()):
        for i in range(out.shape[0]):
            out[i] = face_kind(self.grid, i, a)


def test_across_and_face_kind_under_every_boundary():
    # axis 0: Dirichlet below, Neumann above; axis 1 periodic; J = (member, i, j)
    g = Grid((4, 3), (1.0, 1.0), ((DIRICHLET, NEUMANN), (PERIODIC, PERIODIC)), ((5.0, 0.0), (0.0, 0.0)))
    f = _Faces(g)
    J = np.array([[1, 0, 0], [1, 3, 2], [0, 2, 1]], dtype=np.int32)
    got = {}
    for a in range(2):
        for side in range(2):
            out = np.zeros((3, 4), dtype=np.int32)
            f.across(J, a, side, out)
            got[a, side] = out.tolist()
    assert got[0, 0] == [[1, -1, 0, 0], [1, 2, 2, 1], [0, 1, 1, 1]]  # below the Dirichlet side: the ghost layer
    assert got[0, 1] == [[1, 1, 0, 1], [1, 4, 2, 0], [0, 3, 1, 1]]  # beyond the Neumann side, likewise
    assert got[1, 0] == [[1, 0, 2, 1], [1, 3, 1, 1], [0, 2, 0, 1]]  # periodic: the image
    assert got[1, 1] == [[1, 0, 1, 1], [1, 3, 0, 1], [0, 2, 2, 1]]  # and face n is face 0
    for a, want in ((0, [DIRICHLET, INTERIOR, INTERIOR, INTERIOR, NEUMANN]), (1, [PERIODIC, INTERIOR, INTERIOR, PERIODIC])):
        out = np.zeros(len(want), dtype=np.int32)
        f.kinds(a, out)
        assert out.tolist() == want


def test_exclusive_scan_of_one_row_leaves_the_others():
    counts = np.random.default_rng(1).integers(0, 9, size=(3, 17)).astype(np.int32)
    a = ti.field(ti.i32, shape=counts.shape)
    a.from_numpy(counts)
    total = ti.field(ti.i32, shape=())

    @ti.kernel
    def scan(e: ti.i32, n: ti.i32):
        for _ in range(1):
            total[None] = exclusive_scan(a, e, n)

    scan(1, 12)  # row 1, its first 12 entries
    want = counts.copy()
    want[1, :12] = np.concatenate([[0], np.cumsum(counts[1, :11])])
    assert np.array_equal(a.to_numpy(), want) and total[None] == counts[1, :12].sum()


@pytest.mark.parametrize("n", [1, SCAN_BLOCK - 1, SCAN_BLOCK, SCAN_BLOCK + 1, 3 * SCAN_BLOCK + 17])
def test_block_scan_is_one_serial_pass(n):
    counts = np.random.default_rng(n).integers(0, 9, size=n).astype(np.int32)
    a, sums = ti.field(ti.i32, shape=n), ti.field(ti.i32, shape=-(-n // SCAN_BLOCK))
    total = ti.field(ti.i32, shape=2)
    a.from_numpy(counts)

    @ti.kernel
    def scan():
        block_scan(a, sums, total, 1)

    scan()
    assert np.array_equal(a.to_numpy(), np.concatenate([[0], np.cumsum(counts)[:-1]]))
    assert total[1] == counts.sum() and total[0] == 0


@ti.kernel
def _spreads(n: ti.template(), out: ti.template()):
    for i in ti.static(range(len(n))):
        out[i] = spread(n[i])


def test_spread_gives_a_short_loop_enough_iterations_for_every_thread():
    # a loop over n units made n · spread(n) iterations long: as few as make row_spread(1) (512 a
    # thread on the CPU, where Taichi cuts a range into blocks of 512: 600 units ran 512 on one thread)
    counts = (1, 100, 600, 1023, 1024, 5000, 10**6)
    out = ti.field(ti.i32, shape=len(counts))
    _spreads(counts, out)
    least = row_spread(1)
    for n, s in zip(counts, out.to_numpy()):
        assert n * s >= least and (s == 1 or n * (s - 1) < least)
