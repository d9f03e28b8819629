"""The host's traffic with the device (:mod:`ti_dk.core.traffic`): every kind of touch counted, and
Taichi left as it was."""
import numpy as np
import taichi as ti

from ti_dk.core.traffic import counted


@ti.kernel
def _total(a: ti.template()) -> ti.f64:
    s = 0.0
    for i in a:
        s += a[i]
    return s


@ti.kernel
def _copy(a: ti.template(), b: ti.types.ndarray()):
    for i in a:
        a[i] = b[i]


def test_every_touch_is_counted_and_taichi_restored():
    a = ti.field(ti.f64, shape=10)
    v = ti.Vector.field(3, ti.f32, shape=4)
    before = (type(a).to_numpy, type(a).__getitem__, ti.sync)
    with counted() as t:
        a.from_numpy(np.arange(10.0))  # 80 B written
        _copy(a, np.ones(10))  # an ndarray argument: 80 B written, no return
        assert (t.syncs, t.read, t.written) == (0, 0, 160)
        assert _total(a) == 10.0  # a return value: a sync, 8 B
        a.to_numpy()  # a sync, 80 B
        _ = a[3]  # a sync, 8 B
        v.to_numpy()  # a sync, 4 × 3 × 4 = 48 B
        ti.sync()
        assert (t.syncs, t.read, t.written) == (5, 144, 160)
        _ = v[1]  # an element: its own type, 3 × 4 = 12 B (a Python number would say 8 each)
        _ = ti.field(ti.i32, shape=2)[0]  # 4 B
        assert (t.syncs, t.read) == (7, 160)
        t.reset()
        assert (t.syncs, t.read, t.written) == (0, 0, 0)
    assert (type(a).to_numpy, type(a).__getitem__, ti.sync) == before
    with counted() as t:
        pass
    a.to_numpy()
    assert t.read == 0  # nothing counted once the block is left
