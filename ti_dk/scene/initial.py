"""Initial conditions: each returns the density in particles per cell at the cell centres (or, for
``boltzmann``, cell averages).

``x`` is a tuple of cell-centre coordinate arrays (one per axis, broadcastable to the grid),
measured from the domain's lower corner. Parameters after ``x`` become scene keys, except those in
:data:`CONTEXT`, which :func:`density_ppc` supplies.
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import numpy as np

from ..core.errors import InitError
from ..core.expr import numpy_value, parse, axes_used, VARIABLES

CONTEXT = ("x", "weights")  # arguments density_ppc supplies; the rest are scene keys


def open_regular(path: str | Path):
    """``path`` opened for reading in binary, refused unless it is a regular file: a FIFO or a
    device would make the read wait forever (opened without blocking, so that even a FIFO with no
    writer is only looked at). Raises ``IsADirectoryError`` for a folder, ``OSError`` (``EINVAL``)
    for anything else that is not a file."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(errno.EISDIR, "is a directory", str(path))
        raise OSError(errno.EINVAL, "not a regular file (a FIFO or a device, whose read could wait forever)",
                      str(path))
    return os.fdopen(fd, "rb")


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


def expression(x, density: str = ""):
    """``density``: particles per cell as a formula in x, y, z (:mod:`.expr`), at the cell centres."""
    tree = parse(density)
    extra = sorted(a for a in axes_used(tree) if a >= len(x))
    if extra:
        raise InitError(f"{density!r} uses {VARIABLES[extra[0]]} but the grid is {len(x)}D")
    return np.broadcast_to(numpy_value(tree, x), np.broadcast_shapes(*(a.shape for a in x))).copy()


def array(x, density_file: str = ""):
    """Particles per cell read from ``density_file``: a ``.npy`` file, or ``file.h5:/dataset`` (HDF5),
    shaped like the cells (a relative path is taken from the working directory)."""
    shape = np.broadcast_shapes(*(a.shape for a in x))
    path, _, dataset = str(density_file).partition(".h5:")
    try:
        if dataset:
            import h5py

            with open_regular(path + ".h5") as fh, h5py.File(fh, "r") as f:
                q = np.asarray(f[dataset])
        else:
            with open_regular(density_file) as fh:
                q = np.asarray(np.load(fh, allow_pickle=False))
    except (OSError, KeyError, ValueError, TypeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else f"{type(exc).__name__}: {exc}"
        raise InitError(f"cannot read {density_file!r} ({why}); give a .npy file or file.h5:/dataset") from None
    if q.dtype.kind not in "iuf":  # datetimes, complex numbers, text, booleans would convert, meaning nothing
        raise InitError(f"{density_file!r} holds values of type {q.dtype}: give real numbers (integers or floats)")
    q = q.astype(np.float64)
    if q.shape != shape:
        raise InitError(f"{density_file!r} holds an array of shape {list(q.shape)}: give one of shape {list(shape)} "
                        "(the cells)")
    return q


def boltzmann(x, ppc: float = 5.0, weights=None):
    """On average ``ppc`` particles per cell over the domain, distributed as exp(−U) averaged over
    each cell (the equilibrium of the potential; ``weights``: each cell's share)."""
    if weights is None:
        raise InitError("init 'boltzmann' needs a potential: set potential = \"...\" in [grid]")
    return ppc * weights.size * weights


REGISTRY = {f.__name__: f for f in (uniform, void, ellipses, spheres, expression, array, boltzmann)}


def density_ppc(name: str, params: dict, cells, lengths, potential=None) -> np.ndarray:
    """Evaluate initial condition ``name`` on the cell centres of a grid (particles per cell);
    ``potential`` (:class:`.expr.Potential`) gives ``boltzmann`` its weights."""
    axes = [(np.arange(n) + 0.5) * (L / n) for n, L in zip(cells, lengths)]
    x = tuple(np.meshgrid(*axes, indexing="ij", sparse=True))
    extra = {}
    if name == "boltzmann":
        extra["weights"] = None if potential is None else potential.boltzmann_weights(tuple(cells), tuple(lengths))
    return np.asarray(REGISTRY[name](x, **params, **extra), dtype=np.float64)
