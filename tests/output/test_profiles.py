"""1D runs write one profile PNG per output time: four moment panels, the exact answer, the
particle region shaded."""
import imageio.v3 as iio
import numpy as np
import pytest

from ti_dk import load_scene, run
from ti_dk.output.profiles import ProfileRenderer


def test_void1d_hybrid_writes_a_profile_png_per_output_time(tmp_path):
    scene = load_scene("void1d", method="hybrid", ensemble=40, cells=[40], t_end=0.002,
                       output_times=[0.001, 0.002])
    res = run(scene, out=tmp_path, progress=False)
    assert [p.name for p in res.frames] == ["frame_0000.png", "frame_0001.png"]
    assert res.written["frames"] == tmp_path / "void1d_hybrid_frames"
    img = iio.imread(res.frames[-1]).astype(int)
    assert img.shape[0] >= 600 and img.shape[1] >= 1000
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    shaded = (r > 240) & (g > 215) & (g < 238) & (np.abs(g - b) < 6)  # the light red region band
    grey = (np.abs(r - g) < 4) & (np.abs(g - b) < 4) & (r > 150) & (r < 200)  # the exact curve
    blue = (b > 150) & (r < 80)  # the method's curve (C0)
    assert shaded.sum() > 0.05 * img.shape[0] * img.shape[1]  # the void's 22 of 40 cells, four panels
    # the region lies in the middle half of each panel: columns of shading are in the middle of the picture
    cols = np.flatnonzero(shaded.sum(axis=0) > 50)
    assert 0.15 * img.shape[1] < cols.min() and cols.max() < 0.9 * img.shape[1]
    assert grey.sum() > 2000 and blue.sum() > 1000


def test_exact_answers_drawn_for_periodic_and_stationary_scenes():
    eq = ProfileRenderer(load_scene("equilibrium1d", ppc=5))
    exact, name = eq.exact(0.05)
    assert name == "exact (binomial)"
    assert np.allclose(exact["mean"], 5.0) and np.allclose(exact["variance"], 5.0 * (1 - 1 / 100))
    void = ProfileRenderer(load_scene("void1d"))
    exact, name = void.exact(0.001)
    assert name == "exact (Poisson-binomial, clamped walk)"
    assert np.isclose(exact["mean"].sum(), 20 * 50)  # particles are conserved
    assert void.exact(0.0) == (None, None)
    walled = ProfileRenderer(load_scene("void1d", boundary="neumann"))
    assert walled.exact(0.001) == (None, None)  # no exact answer with walls away from equilibrium


def test_only_1d_scenes():
    with pytest.raises(ValueError, match="1D"):
        ProfileRenderer(load_scene("ellipse2d", cells=[8, 8]))
