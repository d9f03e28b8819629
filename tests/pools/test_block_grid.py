"""The blocks of the pointer pool over the grid (``ti_dk/pools/block_grid.py``): the blocks of cells
on the host against NumPy, and in kernels a cell's block, the neighbour a move goes to and the
source a scan reads, each the other's inverse (wrapped at a periodic side, none beyond a wall)."""
import itertools

import numpy as np
import taichi as ti

from ti_dk.core.grid import NEUMANN, PERIODIC, Grid
from ti_dk.pools.block_grid import BlockGrid
from ti_dk.pools.slots import SIDE

CELLS = (20, 24)  # 3 × 3 blocks of 8 × 8 cells, the first axis's last ones cut short
GRID = Grid(cells=CELLS, lengths=(1.0, 1.2), boundary=((PERIODIC, PERIODIC), (NEUMANN, NEUMANN)),
            reservoir=((0.0, 0.0), (0.0, 0.0)))


def test_blocks_of_cells_on_the_host():
    g, rng = BlockGrid(GRID, 2), np.random.default_rng(1)
    assert (g.side, g.nb, g.NB, g.ndirs, g.periodic) == (SIDE[2], (3, 3), 9, 9, (True, False))
    need = rng.integers(0, 5, size=(2, *CELLS)).astype(float)
    blocks = g.per_block(need, np.sum)
    for e, (i, j) in itertools.product(range(2), itertools.product(range(3), range(3))):
        assert blocks[e, 3 * i + j] == need[e, 8 * i:8 * i + 8, 8 * j:8 * j + 8].sum()
    cells = np.zeros((2, *CELLS), dtype=bool)
    cells[0, 19, 0] = cells[1, 8, 23] = cells[1, 9, 20] = True
    assert g.keys(cells).tolist() == [6, 9 + 5]  # member 0: block (2, 0); member 1: block (1, 2) once


@ti.kernel
def _neighbours(g: ti.template(), out: ti.types.ndarray()):
    """For each block ``B`` and neighbour ``k``: the target, the source whose neighbour ``k`` is ``B``
    (−1: none), the target's source, and the direction of a cell in the target."""
    for B in range(g.NB):
        s = g.coords(B)
        for k in ti.static(range(g.ndirs)):
            T = g.target(s, k)
            S, ok = g.source(s, k)
            back, _ = g.source(g.coords(T), k)
            D = ti.Vector([0, 0, 0])
            for a in ti.static(range(g.dim)):
                D[a + 1] = g.coords(T)[a] * g.side + g.side // 2
            out[B, k, 0] = T
            out[B, k, 1] = S if ok else -1
            out[B, k, 2] = back
            out[B, k, 3] = g.direction(B, D)
            out[B, k, 4] = g.block_of(ti.Vector([D[1], D[2]]))


def test_a_move_and_the_scan_read_the_same_neighbour():
    g = BlockGrid(GRID, 1)
    out = np.zeros((g.NB, g.ndirs, 5), dtype=np.int32)
    _neighbours(g, out)
    for B, (k, d) in itertools.product(range(g.NB), enumerate(g.dirs)):
        i, j = divmod(B, 3)
        T, S, back, code, of = out[B, k]
        assert T == 3 * ((i + d[0]) % 3) + (j + d[1]) % 3 == of
        assert code == k  # a move into the target's cells goes to neighbour k
        if 0 <= j + d[1] < 3:  # not across a wall: the scan at the target finds this block
            assert back == B
        assert S == (3 * ((i - d[0]) % 3) + j - d[1] if 0 <= j - d[1] < 3 else -1)  # no source beyond a wall
