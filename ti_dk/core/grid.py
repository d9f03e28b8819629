"""Grid geometry, boundary kinds and index helpers shared by every solver."""

import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

PERIODIC, NEUMANN, DIRICHLET = 0, 1, 2
_KIND = {"periodic": PERIODIC, "neumann": NEUMANN, "dirichlet": DIRICHLET}


class Geometry:
    """Cell sizes of a box of ``lengths`` cut into ``cells`` (a scene's ``[grid]`` keys or a
    :class:`Grid`): what both derive from those two."""

    cells: tuple[int, ...]
    lengths: tuple[float, ...]

    @property
    def dim(self) -> int:
        """Dimensions: 1, 2 or 3."""
        return len(self.cells)

    @property
    def dx(self) -> tuple[float, ...]:
        """Cell size along each axis."""
        return tuple(L / n for L, n in zip(self.lengths, self.cells))

    @property
    def cell_volume(self) -> float:
        """Volume (1D: length, 2D: area) of a cell."""
        return math.prod(self.dx)


@dataclass(frozen=True)
class Grid(Geometry):
    """A uniform Cartesian grid on ``[0, L_0] × … × [0, L_{d-1}]`` (paper §2.2.1).

    ``boundary[a] = (lo, hi)`` holds the boundary kind of each side of axis ``a``;
    ``reservoir[a]`` the Dirichlet reservoir number density of each side (particles per volume);
    ``potential`` the external potential U (a :class:`ti_dk.core.expr.Potential`, or None).
    """

    cells: tuple[int, ...]
    lengths: tuple[float, ...]
    boundary: tuple[tuple[int, int], ...]
    reservoir: tuple[tuple[float, float], ...]
    potential: object = None  # U in units of k_B T; None compiles no drift anywhere

    @classmethod
    def from_scene(cls, scene) -> "Grid":
        """The grid of a :class:`~ti_dk.scene.schema.Scene`: its boundary kinds as codes, its
        reservoirs as number densities, its potential."""
        vol = math.prod(L / n for L, n in zip(scene.grid.lengths, scene.grid.cells))
        return cls(
            cells=scene.grid.cells,
            lengths=scene.grid.lengths,
            boundary=tuple((_KIND[lo], _KIND[hi]) for lo, hi in scene.grid.boundary),
            reservoir=tuple((lo / vol, hi / vol) for lo, hi in scene.grid.reservoir_ppc),
            potential=scene.grid.potential,
        )

    @property
    def face_area(self) -> tuple[float, ...]:
        """Area of a face normal to each axis."""
        return tuple(self.cell_volume / h for h in self.dx)

    @property
    def reservoir_ppc_max(self) -> float:
        """The largest reservoir density, in particles per cell."""
        return max(max(r) for r in self.reservoir) * self.cell_volume

    @property
    def has_dirichlet(self) -> bool:
        """Whether any side is a Dirichlet reservoir."""
        return any(DIRICHLET in sides for sides in self.boundary)


def numpy_dtype(real):
    """The NumPy dtype of a Taichi real type."""
    return np.float32 if real == ti.f32 else np.float64


def on_cpu() -> bool:
    """Whether Taichi runs on the CPU (after ``ti.init``): where a parallel loop's start and a small
    copy back cost more than the work they save (:func:`light`, :func:`~ti_dk.methods.records.small`)."""
    return ti.lang.impl.current_cfg().arch == ti.cpu


def light(dim: int) -> bool:
    """Whether the *light* loops of a ``dim``-dimensional hybrid (over its ghost cells, covered cells,
    or pool slots) run as serial tasks (``ti.loop_config(serialize=ti.static(light(d)))``): on the
    CPU, where every parallel loop of a launch wakes the pool's threads and waits for them, about
    25 µs on the project's 2 cores whatever the loop's length (an empty one too), and a serial task
    costs about 1 µs. So in 1D and 2D, where those loops are short (ellipse2d: 400–800 ghost cells,
    4–17 k covered, 20–90 k particles; at 300 per cell the particle step's loops but the walk took
    250–285 µs a step, not 355–380). In 3D they are ten times longer (sphere3d 64³: serial made
    the step 3 % slower), and a GPU keeps every loop parallel.
    Evaluated when a kernel compiles (after ``ti.init``)."""
    return on_cpu() and dim <= 2


def row_spread(rows: int) -> int:
    """How many iterations a parallel loop over ``rows`` rows should give each row (one works, the
    others are empty), so that every CPU thread gets rows (1 on other backends and on one thread).

    Taichi 1.7.4's CPU backend (``make_cpu_multithreaded_range_for``, its default) cuts a parallel
    range into one contiguous block per thread of at least 512 iterations, so a loop over the 256
    rows of a 256² grid ran on one thread however many there were. Cutting the rows into pieces
    cost a thread 15 % (the piece's start is not known when the row loop is compiled); empty
    iterations cost nothing measurable."""
    cfg = ti.lang.impl.current_cfg()
    if cfg.arch != ti.cpu or cfg.cpu_max_num_threads < 2:
        return 1
    return -(-512 * cfg.cpu_max_num_threads // max(rows, 1))


@ti.func
def spread(n):
    """:func:`row_spread` for a count ``n`` known only when the kernel runs (a pool's units, the ring's
    cells): loop over ``ti.ndrange(n, spread(n))`` and work where the second index is 0. A walk of
    20,000 particles (600 units) ran 512 units on one thread and 88 on the other."""
    return ti.max(1, (ti.static(row_spread(1)) + n - 1) // ti.max(n, 1))


@ti.func
def wrap(grid: ti.template(), D):
    """Cell ``D`` (no member index; at most one grid length outside it) taken across periodic
    sides, and whether it is a grid cell: the cells near a cell, in Chebyshev distance, as the
    region's rules see them (a Neumann or Dirichlet side has nothing beyond it)."""
    ok = True
    for a in ti.static(range(grid.dim)):
        if ti.static(grid.boundary[a][0] == PERIODIC):  # a select, not `%`: an integer division costs the 3D regrid's
            D[a] += ti.select(D[a] < 0, grid.cells[a], ti.select(D[a] >= grid.cells[a], -grid.cells[a], 0))  # kernels a third
        ok = ok and 0 <= D[a] < grid.cells[a]
    return D, ok


@ti.func
def column_hit(grid: ti.template(), mask: ti.template(), e, C, k) -> bool:
    """Whether ``mask`` (member first, ``(ensemble, *cells)``) is set in member ``e`` within Chebyshev
    distance 1 of cell ``C`` along every axis but the last, at position ``k`` of the last axis (across
    periodic sides, :func:`wrap`; nothing beyond another side). A row's cells read three of these,
    at ``k − 1``, ``k`` and ``k + 1``, each made once for the row: whether the cell is near a set
    cell in 3^(d−1) lookups, not 3^d."""
    d = ti.static(grid.dim)
    D = C
    D[d - 1] = k
    hit = False
    for I in ti.grouped(ti.ndrange(*([3] * (d - 1) or [1]))):
        if ti.static(d > 1):
            for a in ti.static(range(d - 1)):
                D[a] = C[a] + I[a] - 1
        W, ok = wrap(grid, D)
        if ok:
            hit = hit or mask[prefixed(e, W, d)] != 0
    return hit


@ti.func
def offset(o, d: ti.template()):
    """The step ``δ ∈ {−1, 0, 1}^d`` numbered ``o = Σ_a (δ_a + 1) 3^a`` (``0 ≤ o < 3^d``)."""
    off = ti.Vector.zero(ti.i32, d)
    for a in ti.static(range(d)):
        off[a] = (o // 3**a) % 3 - 1
    return off


@ti.func
def prefixed(k, C, d: ti.template()):
    """The index ``(k, *C)`` of cell ``C`` (``d`` axes) in a field whose first index is a member or a
    set: ``k``."""
    J = ti.Vector.zero(ti.i32, d + 1)
    J[0] = k
    for a in ti.static(range(d)):
        J[a + 1] = C[a]
    return J


def row_count(cells: tuple[int, ...]) -> int:
    """The rows of a fixed-order row sum (:func:`row_cell`): the cells along the first axis; in 1D one
    row of all the cells (a member's cells are then summed in order by one thread)."""
    return cells[0] if len(cells) > 1 else 1


@ti.func
def row_cell(i, R, d: ti.template()):
    """Cell ``(i, *R)`` of a ``d``-dimensional grid (``d`` ≥ 2): cell ``R`` of row ``i``, for sums made
    row by row, each row in order, which are the same bits on any thread count."""
    C = ti.Vector.zero(ti.i32, d)
    C[0] = i
    for a in ti.static(range(d - 1)):
        C[a + 1] = R[a]
    return C


@ti.func
def cell_of(x, h, n):
    """Index of the cell of width ``h`` holding coordinate ``x``, clamped into ``[0, n)``."""
    return ti.min(ti.max(ti.cast(ti.floor(x / h), ti.i32), 0), n - 1)


@ti.func
def exclusive_scan(a: ti.template(), e, n):
    """Replace ``a[e, 0:n]`` by its exclusive prefix sums, serially, and return their total: the
    middle pass of every count–scan–scatter (pool compaction, the particles' cell-order sort).

    Call it from a loop under ``ti.loop_config(serialize=True)``, as every short loop of a kernel
    (over a few members) should be: a parallel loop is a task of Taichi's CPU thread pool, whose
    start and end cost tens of microseconds whatever the loop does, and a hybrid step runs some
    twenty of them."""
    total = 0
    for k in range(n):
        c = a[e, k]
        a[e, k] = total
        total += c
    return total


SCAN_BLOCK = 256  # entries one thread scans in block_scan (its serial part is this many times shorter)


@ti.func
def block_scan(a: ti.template(), sums: ti.template(), total: ti.template(), slot: ti.template()):
    """Replace the 1-axis i32 field ``a`` by its exclusive prefix sums and put their total in
    ``total[slot]``, by blocks: each block of :data:`SCAN_BLOCK` entries scanned by one thread, in
    parallel; the block totals (``sums``, i32 scratch of ⌈len(a) / SCAN_BLOCK⌉) scanned by one;
    each block's offset added, in parallel. The result of one serial pass (integers), with a serial
    part SCAN_BLOCK times shorter: a GPU runs a serial loop on one of its threads. Call it at a
    kernel's top level (its loops are then parallel tasks)."""
    N, B = ti.static(a.shape[0], SCAN_BLOCK)
    for b in range((N + B - 1) // B):
        t = 0
        for k in range(b * B, ti.min(b * B + B, N)):
            c = a[k]
            a[k] = t
            t += c
        sums[b] = t
    ti.loop_config(serialize=True)
    for _ in range(1):
        t = 0
        for b in range((N + B - 1) // B):
            c = sums[b]
            sums[b] = t
            t += c
        total[slot] = t
    for k in range(N):
        a[k] += sums[k // B]


INTERIOR = -1  # face_kind of a face that is not on the boundary


@ti.func
def across(grid: ti.template(), J, a: ti.template(), side: ti.template()):
    """The cell across face ``side`` (0: lower, 1: upper) of cell ``J`` along axis ``a``, and
    whether it is a grid cell: the one ghost-layer rule every solver uses (paper §2.2.1).

    ``J`` carries the member index first (axis ``a`` is component ``a + 1``). A periodic side
    wraps (the image is a grid cell); beyond a Neumann or Dirichlet side the result is the
    ghost-layer index (−1 or ``n_a``) and ``False``: the caller mirrors the cell (Neumann: no
    gradient, no flux) or takes the reservoir density (Dirichlet). For ``side = 1`` the result
    is also the index of the upper face of ``J`` in a face array (the periodic image of face
    ``n_a`` being face 0). ``clustering.grow`` applies the same rule to NumPy masks with ``np.roll``.
    """
    K = J
    inside = True
    n = ti.static(grid.cells[a])
    if ti.static(side == 0):
        K[a + 1] -= 1
        if ti.static(grid.boundary[a][0] == PERIODIC):
            if K[a + 1] < 0:
                K[a + 1] = n - 1
        else:
            inside = K[a + 1] >= 0
    else:
        K[a + 1] += 1
        if ti.static(grid.boundary[a][1] == PERIODIC):
            if K[a + 1] == n:
                K[a + 1] = 0
        else:
            inside = K[a + 1] < n
    return K, inside


@ti.func
def face_kind(grid: ti.template(), i, a: ti.template()):
    """The boundary kind of face ``i`` along axis ``a`` (faces ``0 … n_a``; face ``i`` is the lower
    face of cell ``i``), or :data:`INTERIOR`."""
    kind = INTERIOR
    if i == 0:
        kind = grid.boundary[a][0]
    elif i == grid.cells[a]:
        kind = grid.boundary[a][1]
    return kind
