"""The method registry: every scene method has a builder, and each builds its solver initialised."""
import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.control.registry import BUILDERS, make_solver
from ti_dk.methods.solver import Solver
from ti_dk.scene.schema import METHODS


def test_every_method_has_a_builder():
    assert set(BUILDERS) == set(METHODS)


@pytest.mark.parametrize("method", METHODS)
def test_each_builder_makes_an_initialised_solver(method):
    scene = load_scene("void1d", method=method, ensemble=2, cells=[20])
    s = make_solver(scene, scene.initial_ppc)
    assert isinstance(s, Solver)
    counts = s.density() * scene.grid.cell_volume
    assert counts.shape == (2, 20)
    if method == "particle":  # sampled: whole particles around the initial profile
        assert np.array_equal(counts, np.round(counts)) and counts.sum() > 0
    else:
        assert np.allclose(counts, scene.initial_ppc[None])
    assert (s.region() is not None) == (method == "hybrid")
