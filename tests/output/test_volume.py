"""The 3D frames' volume panel (:class:`ti_dk.output.volume.Volume`): shells in the colour bar's
colours, on a linear and a log scale."""
import matplotlib
import numpy as np
import pytest
from matplotlib.colors import LogNorm, Normalize

from ti_dk.output.volume import Volume

VIRIDIS = matplotlib.colormaps["viridis"]


@pytest.mark.parametrize("norm", [Normalize(0.0, 50.0), LogNorm(0.1, 50.0)], ids=["linear", "log"])
def test_the_ray_through_a_ball_composites_its_shells_in_the_colour_bars_colours(norm):
    """A ball of density m = 30 on 32³ cells: the ray through its centre crosses the shells at
    m/4 and 0.6 m on the way in and out (normal to them: shade 1), each with opacity 0.3, then
    reaches the grey background, so the pixel is 0.3 (c₁ + 0.7 c₂ + 0.49 c₂ + 0.343 c₁) + 0.7⁴ 0.93,
    c the level's colour on the colour bar's scale (on a log scale far from the linear one's)."""
    n, m = 32, 30.0
    X, Y, Z = np.meshgrid(*[(np.arange(n) + 0.5) / n - 0.5] * 3, indexing="ij")
    ppc = np.where(X**2 + Y**2 + Z**2 < 0.3**2, m, 0.0)
    v = Volume((n, n, n), VIRIDIS, norm, m)
    img = v.render(ppc, None, 128)
    assert v.levels == [7.5, 18.0]
    c1, c2 = (np.array(VIRIDIS(norm(level))[:3]) for level in v.levels)
    a = Volume.SHELL
    expected = a * (c1 + (1 - a) * c2 + (1 - a) ** 2 * c2 + (1 - a) ** 3 * c1) + (1 - a) ** 4 * 0.93
    assert np.abs(img[64, 64] - expected).max() < 0.01, (img[64, 64], expected)
    assert np.abs(img[2, 2] - 0.93).max() < 1e-9  # a ray that misses the ball: the background
