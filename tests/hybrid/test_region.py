"""The particle region: independence of the box layout (one ghost set per cell)."""
import numpy as np

from ti_dk import load_scene
from ti_dk.control.registry import make_solver
from ti_dk.hybrid.clustering import mask


def test_box_layout_does_not_matter_and_shared_ghosts_are_sampled_once():
    scene = load_scene("equilibrium1d", method="hybrid", cells=[16, 16], regrid_interval=0, threshold=1, ppc=3,
                       t_equil=None, histogram=None, seed=7, ensemble=1)
    one = [((2, 2), (7, 12)), ((8, 2), (12, 12))]  # two boxes with a one-cell gap (x = 7) between them
    other = [((2, 2), (5, 7)), ((2, 7), (7, 12)), ((5, 2), (7, 7)), ((8, 2), (12, 5)), ((8, 5), (12, 12))]
    assert np.array_equal(mask(one, (16, 16)), mask(other, (16, 16)))
    final = []
    for boxes in (one, other):
        s = make_solver(scene, scene.initial_ppc)
        s.set_region(mask(boxes, (16, 16))[None], 0)
        # 3 particles per cell everywhere: the ghost ring gets exactly 3 per ghost cell, once each,
        # the gap column included although it borders both boxes
        s.sampler.fill(s.pool, s.cur, 0, s.n_ring, 0.0, 1, 0)
        n_ghost = s.pool.n.to_numpy()[s.cur, 0] - s.n_real.to_numpy()[0]
        assert n_ghost == 3 * s.regions.ring_mask.sum() == 3 * (12 * 12 - 9 * 10)
        for n in range(30):
            s.step(n)
        final.append(s.density())
    assert np.array_equal(final[0], final[1])
