"""The host's traffic with the device, counted: syncs and bytes read back and written.

On a GPU every sync waits for the device and every copy crosses the bus, so a step's host traffic
is a cost of its own (a hybrid step reads back a few counts: ``benchmarks/readback.py``).
:func:`counted` wraps every way Taichi's Python scope touches device data, for as long as its
``with`` block runs, so that no code path escapes the count: a field's ``to_numpy`` and element
reads (a sync and a copy back), a kernel's return value (a sync and one scalar), ``ti.sync`` (a
sync), and the other way ``from_numpy`` and NumPy arrays passed to kernels as ndarray arguments.
Written for Taichi 1.7.x's class names.
"""
import importlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import taichi as ti
from taichi.lang.util import to_numpy_type


@dataclass
class Traffic:
    """What the host did with the device since the last :meth:`reset`."""

    syncs: int = 0  # waits for the device
    read: int = 0  # bytes copied back [B]
    written: int = 0  # bytes copied to the device [B]

    def reset(self) -> None:
        """Count from zero again."""
        self.syncs = self.read = self.written = 0


def _wrapped(original, count, depth: list[int]):
    """``original`` counted by ``count(result, *args)``, unless called inside another counted call
    (``to_numpy`` runs a kernel of its own: one touch, not two)."""
    def call(*args, **kwargs):
        depth[0] += 1
        try:
            out = original(*args, **kwargs)
        finally:
            depth[0] -= 1
        if depth[0] == 0:
            count(out, *args)
        return out

    return call


@contextmanager
def counted() -> Iterator[Traffic]:
    """Count the host's traffic with the device inside the ``with`` block (Taichi is restored after)."""
    t = Traffic()

    def read(out, *_):
        t.syncs += 1
        t.read += np.asarray(out).nbytes

    def element(out, field, *_):  # the field's own type: a Python number would count 8 bytes whatever it is
        t.syncs += 1
        t.read += np.size(out.to_numpy() if hasattr(out, "to_numpy") else out) * np.dtype(to_numpy_type(field.dtype)).itemsize

    def written(_out, _field, array, *_):
        t.written += np.asarray(array).nbytes

    def kernel(out, _kernel, *args):
        t.written += sum(a.nbytes for a in args if isinstance(a, np.ndarray))
        if out is not None:
            read(out)

    field = importlib.import_module("taichi.lang.field")
    matrix = importlib.import_module("taichi.lang.matrix")
    kernel_impl = importlib.import_module("taichi.lang.kernel_impl")
    patches = [(cls, name, count) for cls in (field.ScalarField, matrix.MatrixField)
               for name, count in (("to_numpy", read), ("__getitem__", element), ("from_numpy", written))]
    patches.append((kernel_impl.Kernel, "__call__", kernel))
    saved = [(cls, name, cls.__dict__.get(name)) for cls, name, _ in patches]  # None: inherited
    sync = ti.sync

    def counted_sync():
        t.syncs += 1
        sync()

    depth = [0]
    try:
        for cls, name, count in patches:
            setattr(cls, name, _wrapped(getattr(cls, name), count, depth))
        ti.sync = counted_sync
        yield t
    finally:
        for cls, name, original in saved:
            if original is None:
                delattr(cls, name)
            else:
                setattr(cls, name, original)
        ti.sync = sync
