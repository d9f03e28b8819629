"""S(k) in the run file and its PNG: dataset, wave numbers, exact answers per scene, shells,
checkpoints."""
import h5py
import numpy as np

from ti_dk import load_scene, run
from ti_dk.core import spectra, theory
from ti_dk.output.spectra import binned, exact_structure_factor, radial_bins


def test_run_file_holds_s_of_k_with_its_wave_numbers_and_the_png(tmp_path):
    scene = load_scene("equilibrium1d", method="gaussian", cells=[12, 10], lengths=[1.0, 2.0], ensemble=30,
                       t_equil=None, histogram=None, t_end=0.002, output_times=[0.001], structure_factor=True)
    res = run(scene, out=tmp_path, snapshots=False)
    png = tmp_path / "equilibrium1d_gaussian_frames" / "structure_factor.png"
    assert res.written["structure factor"] == png and png.stat().st_size > 10_000
    with h5py.File(res.path) as f:
        ds = f["stats/structure_factor"]
        assert ds.shape == (2, 12, 6) and np.array_equal(ds[:], res.stats.structure_factor)
        assert np.allclose(ds.attrs["k0"], 2 * np.pi * np.fft.fftfreq(12, 1 / 12))
        assert np.allclose(ds.attrs["k1"], np.pi * np.arange(6))
        assert "N_total" in ds.attrs["definition"]
    # a single member has no ensemble S(k): neither dataset nor picture
    one = run(scene.replace(ensemble=1), out=tmp_path / "one", snapshots=False)
    assert "structure factor" not in one.written
    with h5py.File(one.path) as f:
        assert "structure_factor" not in f["stats"]


def test_exact_answer_per_scene():
    """Particles: 1 (exact_uniform) or the walk's relaxation; fv/gaussian: the linear scheme at the
    row's steps; none for the hybrid, walls or a non-uniform start."""
    base = dict(cells=[16], t_equil=None, histogram=None)
    sc = load_scene("equilibrium1d", method="particle", particle_init="exact_uniform", **base)
    S, _ = exact_structure_factor(sc, 7)
    assert S.shape == (9,) and S[0] == 0 and np.all(S[1:] == 1)
    sc = load_scene("equilibrium1d", method="particle", ppc=2.5, **base)
    assert np.allclose(exact_structure_factor(sc, 7)[0],
                       spectra.half(theory.particle_structure_factor(2.5, (16,), (1.0,), sc.dt, 7)))
    sc = load_scene("equilibrium1d", method="fv", C=0.2, **base)
    pooled = range(3, 40, 5)
    assert np.allclose(exact_structure_factor(sc, pooled)[0],
                       spectra.half(theory.linear_structure_factor((16,), (0.2,), pooled)))
    for other in (dict(method="hybrid"), dict(boundary="neumann"), dict(init="void")):
        assert exact_structure_factor(load_scene("equilibrium1d", **base | other), 7)[0] is None


def test_shells_hold_every_independent_mode_once():
    cells, lengths = (12, 9), (1.0, 2.0)
    shell, k = radial_bins(cells, lengths)
    use = spectra.independent_modes(cells)
    use.flat[0] = False
    assert np.array_equal(shell >= 0, use) and np.all(np.diff(k) > 0)
    assert np.allclose(binned(np.full(shell.shape, 2.5), shell), 2.5)
    kk = spectra.magnitude(cells, lengths)
    assert np.all(np.abs(binned(kk, shell)[shell[use]] - kk[use]) <= 2 * np.pi / max(lengths) + 1e-12)  # shells one 2π/L wide


def test_a_restarted_stationary_run_has_the_same_s_of_k(tmp_path):
    scene = load_scene("equilibrium1d", method="gaussian", cells=[20], ensemble=8, t_end=0.01, t_equil=0.004,
                       sample_every=5, structure_factor=True)
    whole = run(scene, out=tmp_path / "whole", frames=False)
    run(scene, out=tmp_path / "first", frames=False, checkpoint_every=40)  # 64 steps, pooling from 26
    resumed = run(scene, out=tmp_path / "second", frames=False,
                  restart=tmp_path / "first" / "equilibrium1d_gaussian_checkpoint.h5")
    assert np.array_equal(whole.stats.structure_factor, resumed.stats.structure_factor)
    assert whole.stats.structure_factor.shape == (1, 11)
