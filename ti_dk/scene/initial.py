"""Initial conditions: each returns the density in particles per cell at the cell centres.

``x`` is a tuple of cell-centre coordinate arrays (one per axis, broadcastable to the grid),
measured from the domain's lower corner. Parameters after ``x`` become scene keys.
"""
from __future__ import annotations

import numpy as np


def uniform(x, ppc: float = 5.0):
    """The same mean number of particles in every cell."""
    return np.full(np.broadcast_shapes(*(a.shape for a in x)), ppc)


def void(x, ppc: float = 20.0, void_lo: float = 0.25, void_hi: float = 0.75):
    """``ppc`` particles per cell, except none where ``void_lo <= x_0 <= void_hi`` (paper §4, Fig. 4)."""
    q = uniform(x, ppc)
    q[np.broadcast_to((x[0] >= void_lo) & (x[0] <= void_hi), q.shape)] = 0.0
    return q


def ellipses(x, ppc_outer: float = 30.0, ppc_inner: float = 15.0, outer_r: float = 0.4, inner_r: float = 0.1):
    """Two crossed ellipses in the unit square (paper Fig. 5, as in the authors' code).

    From the centre (0.5, 0.5): ``ppc_outer`` where 0.5(x−y)² + 2(x+y)² > outer_r², else
    ``ppc_inner`` where 2(x−y)² + 0.5(x+y)² < inner_r², else empty.
    """
    u, v = x[0] - 0.5, x[1] - 0.5
    outer = 0.5 * (u - v) ** 2 + 2.0 * (u + v) ** 2 > outer_r**2
    inner = 2.0 * (u - v) ** 2 + 0.5 * (u + v) ** 2 < inner_r**2
    return np.where(outer, ppc_outer, np.where(inner, ppc_inner, 0.0))


def spheres(x, ppc_outer: float = 30.0, ppc_inner: float = 15.0, outer_r: float = 0.4, inner_r: float = 0.1,
            inner_x: float = 0.1, inner_y: float = 0.2, inner_z: float = 0.0):
    """A void sphere holding a smaller offset sphere, in the unit cube (paper Fig. 7).

    From the centre (0.5, 0.5, 0.5): ``ppc_outer`` where x² + y² + z² > outer_r², else
    ``ppc_inner`` where (x − inner_x)² + (y − inner_y)² + (z − inner_z)² < inner_r², else empty.
    """
    u, v, w = (a - 0.5 for a in x)
    outer = u**2 + v**2 + w**2 > outer_r**2
    inner = (u - inner_x) ** 2 + (v - inner_y) ** 2 + (w - inner_z) ** 2 < inner_r**2
    return np.where(outer, ppc_outer, np.where(inner, ppc_inner, 0.0))


REGISTRY = {f.__name__: f for f in (uniform, void, ellipses, spheres)}


def density_ppc(name: str, params: dict, cells, lengths) -> np.ndarray:
    """Evaluate initial condition ``name`` on the cell centres of a grid (particles per cell)."""
    axes = [(np.arange(n) + 0.5) * (L / n) for n, L in zip(cells, lengths)]
    x = tuple(np.meshgrid(*axes, indexing="ij", sparse=True))
    return np.asarray(REGISTRY[name](x, **params), dtype=np.float64)
