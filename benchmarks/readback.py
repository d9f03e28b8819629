"""What a hybrid step costs the host: device syncs and bytes read back and written, per step.

    PYTHONPATH=. python benchmarks/readback.py ellipse2d --set cells=[64,64] --steps 200
    PYTHONPATH=. python benchmarks/readback.py sphere3d --set cells=[32,32,32] --steps 100

Every way Taichi's Python scope touches device data is counted by wrapping it (nothing in ti_dk is
changed, so no code path escapes): a field's ``to_numpy`` and element reads (a sync and a copy
back), a kernel's return value (a sync and one scalar), ``ti.sync`` (a sync, no bytes), and the
host-to-device side, ``from_numpy`` and NumPy arrays passed to kernels as ndarray arguments. The
scene runs as ``make_solver`` builds it, stepped ``--steps`` times; steps with a regrid or an
extension (the regrid log grew) are reported apart from the others. On a GPU each sync waits for
the device and each copy crosses PCIe: this is the host's share of a step that issue 40 asks to
keep under 64 bytes read on average.
"""
import argparse
import importlib

import numpy as np
import taichi as ti

import ti_dk
from ti_dk.control.registry import make_solver
from ti_dk.scene.load import command_overrides

COUNT = {"syncs": 0, "read": 0, "written": 0}


def _wrap(cls, name: str, count) -> None:
    """Replace ``cls.name`` by a wrapper that calls ``count(result, *args)`` after the original."""
    original = getattr(cls, name)

    def wrapped(*args, **kwargs):
        out = original(*args, **kwargs)
        count(out, *args)
        return out

    setattr(cls, name, wrapped)


def _read(out, *_) -> None:
    COUNT["syncs"] += 1
    COUNT["read"] += np.asarray(out).nbytes


def _written(_out, _field, array, *rest) -> None:
    COUNT["written"] += np.asarray(array).nbytes


def _kernel(out, _kernel, *args) -> None:
    COUNT["written"] += sum(a.nbytes for a in args if isinstance(a, np.ndarray))
    if out is not None:
        COUNT["syncs"] += 1
        COUNT["read"] += np.asarray(out).nbytes


def instrument() -> None:
    """Wrap Taichi's Python-scope data paths (Taichi 1.7.x class names)."""
    field = importlib.import_module("taichi.lang.field")
    matrix = importlib.import_module("taichi.lang.matrix")
    kernel = importlib.import_module("taichi.lang.kernel_impl")
    for cls in (field.ScalarField, matrix.MatrixField):
        _wrap(cls, "to_numpy", _read)
        _wrap(cls, "__getitem__", _read)
        _wrap(cls, "from_numpy", _written)
    _wrap(kernel.Kernel, "__call__", _kernel)
    sync = ti.sync

    def counted_sync():
        COUNT["syncs"] += 1
        sync()

    ti.sync = counted_sync


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    ti_dk.init("cpu", args.threads)
    scene = ti_dk.load_scene(args.scene, method="hybrid", **command_overrides(args.set, {}))
    solver = make_solver(scene, scene.initial_ppc)
    instrument()
    rows = []
    for n in range(min(args.steps, scene.n_steps)):
        before = len(solver.regrids)
        COUNT.update(syncs=0, read=0, written=0)
        solver.step(n)
        rows.append((len(solver.regrids) > before, COUNT["syncs"], COUNT["read"], COUNT["written"]))
    rows = np.array(rows, dtype=np.int64)
    h = scene.hybrid
    print(f"{args.scene} {'x'.join(map(str, scene.grid.cells))}, {solver.ensemble} member(s), region_from {h.region_from}, "
          f"regrid_floor {h.regrid_floor:g}, {len(rows)} steps (step 0's setup regrid not counted)")
    print("| steps | count | syncs / step | bytes read / step (max) | bytes written / step (max) |")
    print("|---|---|---|---|---|")
    for label, pick in (("all", np.ones(len(rows), bool)), ("with a regrid or extension", rows[:, 0] == 1),
                        ("without", rows[:, 0] == 0)):
        r = rows[pick]
        if len(r):
            print(f"| {label} | {len(r)} | {r[:, 1].mean():.1f} | {r[:, 2].mean():,.0f} ({r[:, 2].max():,}) | "
                  f"{r[:, 3].mean():,.0f} ({r[:, 3].max():,}) |")


if __name__ == "__main__":
    main()
