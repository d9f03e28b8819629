"""A run's series over time: the two-state rate is exact on its own model, and the crossing rate of
the double well from its left/right observables (one command, from the result or the run file)
matches the exact rate of the 1D walk (``theory.walk_crossing_fraction``, as
``benchmarks/kramers1d.py`` computes it)."""
import warnings

import h5py
import numpy as np
import pytest

import ti_dk
from ti_dk.core import theory
from ti_dk.core.expr import derivative, numpy_value
from ti_dk.output.series import crossing_rate, mean_se, two_state_rate

FORMULA = "2*(x-0.3)**2*(x-0.7)**2/5e-4"  # doublewell2d's potential along x (kramers1d.py)
BLOB = "exp(-((x-0.3)**2*(x-0.7)**2)/5e-4)*step(x-0.2)*step(0.4-x)"  # its start along x


def test_two_state_rate_is_exact_on_the_two_state_model():
    t = np.linspace(0, 0.05, 11)
    k = np.array([0.1, 2.0, 7.5])
    f = (1 - np.exp(-2 * k[:, None] * t)) / 2
    assert two_state_rate(t, f, 0.01) == pytest.approx(k, rel=1e-10)
    with pytest.raises(ValueError, match="t_from = 0.06 leaves 0 record"):
        two_state_rate(t, f, 0.06)


def test_mean_se_is_the_standard_error_over_members():
    mean, se = mean_se(np.array([[1.0, 2.0, 3.0, 6.0]]))
    assert mean == pytest.approx([3.0]) and se == pytest.approx([np.sqrt(14 / 3) / 2])
    assert np.isnan(mean_se(np.array([[4.0]]))[1]).all()


def test_the_double_well_crossing_rate_matches_the_exact_walk(tmp_path):
    # the x part of doublewell2d (separable: the 2D particles' crossing fraction is this 1D walk's),
    # coarse (16 cells, 640 steps) so it runs in seconds; the scene's own left/right observables
    with warnings.catch_warnings():  # the drift near the empty walls exceeds a cell: the clamp warning
        warnings.simplefilter("ignore")
        scene = ti_dk.load_scene("doublewell2d", method="particle", compare=None, cells=[16], C=0.02, t_end=0.05,
                                 potential=FORMULA, density=f"2500*{BLOB}", ensemble=40, output_times=[],
                                 sample_every=64, seed=5)
    assert dict(scene.stats.observables) == {"left": "x < 0.5", "right": "x > 0.5"}
    res = ti_dk.run(scene, out=tmp_path, progress=False)
    rate = ti_dk.crossing_rate(res, t_from=0.01)
    assert rate == crossing_rate(res.path, "left", "right", t_from=0.01)  # the run file gives the same
    t = res.series["time"]
    assert t.tolist() == pytest.approx(np.arange(11) * 64 * scene.dt)
    du = derivative(scene.potential.tree, 0)
    f = theory.walk_crossing_fraction(lambda x: numpy_value(du, (x,)), scene.initial_ppc, scene.dt, t, sub=128)
    exact = float(two_state_rate(t, f, 0.01))
    assert exact == pytest.approx(0.1124, abs=5e-4)  # kramers1d's 0.1120 at 32 cells; 0.1125 at 16
    assert rate.members == 40 and rate.se < 0.08 * exact  # a test that can fail: about 5 % here
    assert abs(rate.value - exact) < 4 * rate.se, (rate, exact)
    # particles: the two wells hold every particle of each member, exactly
    left, right = res.series["left"], res.series["right"]
    assert np.array_equal(left + right, res.series["mass"]) and np.all(left == np.round(left))
    with h5py.File(res.path) as fh:
        assert fh["observables/left"].shape == (11, 40) and "per member" in fh["observables/left"].attrs["units"]
    assert (tmp_path / "doublewell2d_particle_frames" / "observables.png").stat().st_size > 0
    assert (tmp_path / "doublewell2d_particle_frames" / "series.png").stat().st_size > 0
    with pytest.raises(ValueError, match="no observable 'top': it has left, right; add it to"):
        crossing_rate(res, "top", "right")
