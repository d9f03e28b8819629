"""The solver contract's defaults, and the snapshot of a solver with a particle region."""
import numpy as np

from ti_dk.methods.solver import RegionSolver, Solver


class Plain(Solver):
    def density(self):
        return np.arange(6.0).reshape(2, 3)


class WithRegion(RegionSolver):
    boxes = [[((1,), (3,))], []]

    def density(self):
        return np.zeros((2, 4))

    def region(self):
        return np.array([[0, 1, 1, 0], [0, 0, 0, 0]], dtype=bool)

    def state(self):
        return {"n_real": np.array([2, 0]), "x": np.array([[[1.5], [2.5], [9.0]], [[0.0], [0.0], [0.0]]]),
                "pid": np.arange(12, dtype=np.uint32).reshape(2, 3, 2)}


def test_defaults_ask_nothing_of_a_solver_without_a_region():
    s = Plain()
    assert dict(s.timing) == {} and list(s.regrids) == [] and not s.boxes and s.region() is None
    snap = s.snapshot(1)
    assert snap.density.tolist() == [3.0, 4.0, 5.0]
    assert snap.region is None and snap.positions is None and snap.pid is None and snap.boxes is None


def test_a_region_solver_snapshots_its_region_particles_and_boxes():
    snap = WithRegion().snapshot(0)
    assert snap.region.tolist() == [False, True, True, False]
    assert snap.positions.tolist() == [[1.5], [2.5]]  # only the member's live particles
    assert snap.pid.tolist() == [[0, 1], [2, 3]]
    assert snap.boxes.tolist() == [[1, 3]] and snap.boxes.dtype == np.int64
    assert WithRegion().snapshot(1).boxes.shape == (0, 2)
