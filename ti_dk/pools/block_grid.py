"""The grid cut into the blocks of a :class:`~.blocks.BlockPool` (:class:`BlockGrid`): which block a
cell lies in, a block's coordinates, and its ``3^dim`` neighbours in a fixed order."""

import itertools
import math

import numpy as np
import taichi as ti

from .slots import SIDE


@ti.data_oriented
class BlockGrid:
    """The blocks of :data:`SIDE` cells per axis over ``grid`` (the last ones cut by the grid's edge);
    block ``B`` is the C-order index of its coordinates. No fields: geometry only, on the host and
    in kernels. A particle moves at most one cell per step, so a block sends particles to one of
    the ``3^dim`` neighbours in :attr:`dirs` (neighbour ``k`` in the direction ``dirs[k]``)."""

    def __init__(self, grid, ensemble: int):
        self.dim, self.cells, self.ensemble = grid.dim, tuple(grid.cells), ensemble
        self.side = SIDE[self.dim]
        self.nb = tuple(-(-m // self.side) for m in self.cells)  # blocks per axis
        self.NB = math.prod(self.nb)
        assert ensemble * self.NB < 2**31, "block keys are 32-bit"
        self.periodic = tuple(lo == 0 for lo, _ in grid.boundary)  # grid.PERIODIC
        self.dirs = list(itertools.product((-1, 0, 1), repeat=self.dim))  # neighbour blocks, code = index
        self.ndirs = len(self.dirs)

    # -- host -----------------------------------------------------------------------------
    def per_block(self, a: np.ndarray, reduce) -> np.ndarray:
        """``reduce`` (``np.any``, ``np.sum``) of ``(ensemble, *cells)`` values over each block's
        cells: ``(ensemble, NB)``."""
        pad = [(0, 0)] + [(0, b * self.side - m) for b, m in zip(self.nb, self.cells)]
        c = np.pad(a, pad).reshape(self.ensemble, *[v for b in self.nb for v in (b, self.side)])
        return reduce(c, axis=tuple(range(2, 2 + 2 * self.dim, 2))).reshape(self.ensemble, self.NB)

    def keys(self, cells: np.ndarray) -> np.ndarray:
        """Keys ``e·NB + B`` of the blocks holding any of ``cells`` (``(ensemble, *cells)`` booleans), ascending."""
        return np.flatnonzero(self.per_block(cells, np.any)).astype(np.int32)

    # -- kernels --------------------------------------------------------------------------
    @ti.func
    def block_of(self, C):
        """The block of cell ``C`` (a reservoir cell beyond the grid: the boundary block)."""
        B = 0
        for a in ti.static(range(self.dim)):
            B = B * self.nb[a] + ti.min(ti.max(C[a], 0), self.cells[a] - 1) // self.side
        return B

    @ti.func
    def coords(self, B):
        """The coordinates of block ``B``."""
        c = ti.Vector.zero(ti.i32, self.dim)
        for k in ti.static(range(self.dim)):
            a = ti.static(self.dim - 1 - k)
            c[a] = B % self.nb[a]
            B //= self.nb[a]
        return c

    @ti.func
    def linear(self, c):
        """The block at coordinates ``c``."""
        B = 0
        for a in ti.static(range(self.dim)):
            B = B * self.nb[a] + c[a]
        return B

    @ti.func
    def direction(self, B, D):
        """``k``: the block of cell ``D`` (member first) is neighbour ``k`` of block ``B`` (a step
        moves at most one cell per axis; across a periodic side the blocks wrap)."""
        s = self.coords(B)
        k = 0
        for a in ti.static(range(self.dim)):
            d = D[a + 1] // self.side - s[a]
            if d > 1:  # across a periodic side
                d -= self.nb[a]
            elif d < -1:
                d += self.nb[a]
            k = k * 3 + d + 1
        return k

    @ti.func
    def source(self, t, k: ti.template()):
        """The block whose neighbour ``k`` is the block at coordinates ``t``, and whether there is one
        (none beyond a side that is not periodic)."""
        s = t
        ok = True
        for a in ti.static(range(self.dim)):
            s[a] -= self.dirs[k][a]
            if s[a] < 0 or s[a] >= self.nb[a]:
                if ti.static(self.periodic[a]):
                    s[a] = (s[a] + self.nb[a]) % self.nb[a]
                else:
                    ok = False
        return self.linear(s), ok

    @ti.func
    def target(self, s, k: ti.template()):
        """Neighbour ``k`` of the block at coordinates ``s`` (wrapped at every side)."""
        t = s
        for a in ti.static(range(self.dim)):
            t[a] = (t[a] + self.dirs[k][a] + self.nb[a]) % self.nb[a]
        return self.linear(t)
