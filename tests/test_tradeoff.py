"""The trade's error measures are calibrated on the exact method and its Pareto front is exact."""
import numpy as np

from ti_dk import load_scene, run, tradeoff


def test_pareto_front():
    cost = np.array([1.0, 2.0, 3.0, 1.5, 4.0])
    err = np.array([5.0, 2.0, 1.0, 6.0, 1.0])
    assert tradeoff.pareto(cost, err).tolist() == [True, True, True, False, False]


def test_errors_are_one_for_the_exact_method_and_not_for_the_gaussian():
    common = dict(ensemble=600, t_end=0.0025, output_times=[0.0025])
    part = run(load_scene("void1d", method="particle", **common))
    gau = run(load_scene("void1d", method="gaussian", **common))
    e_part = tradeoff.void_error(part, 600, part.times[-1])
    e_gau = tradeoff.void_error(gau, 600, gau.times[-1])
    assert all(0.5 < e_part[k] < 1.6 for k in tradeoff.KEYS), e_part
    assert e_gau["skewness"] > 4, e_gau
    ell = run(load_scene("ellipse2d", method="particle", cells=[32, 32], compare="none", t_end=0.00096))
    assert 0.85 < tradeoff.ellipse_error(ell, ell.times[-1])["chi2"] < 1.15


def test_criterion_picks_the_smallest_threshold_within_tolerance():
    rows = [{"setting": f"hybrid threshold {t}", "error": e} for t, e in ((1, 3.0), (2, 1.9), (5, 1.2), (10, 2.5))]
    assert tradeoff.criterion(rows + [{"setting": "fv", "error": 0.5}], tolerance=2.0) == 2.0
    assert tradeoff.criterion(rows) == 5.0
