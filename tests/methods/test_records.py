"""A run's per-member record summed on the device (:mod:`ti_dk.methods.records`) against NumPy's sums."""
import numpy as np
import pytest
import taichi as ti

from ti_dk import load_scene
from ti_dk.core.grid import Grid
from ti_dk.methods.records import MemberSums, Scalars


@pytest.mark.parametrize("cells", [[13], [9, 7], [5, 4, 6]])
def test_the_record_is_numpys_sums(cells):
    rng = np.random.default_rng(len(cells))
    grid, E = Grid.from_scene(load_scene("ellipse2d", cells=cells, init="uniform")), 3
    q = rng.normal(2.0, 3.0, size=(E, *cells))  # some negative
    region = rng.uniform(size=(E, *cells)) < 0.4
    sets = {"a": rng.uniform(size=cells) < 0.5, "b": np.ones(cells, dtype=bool)}
    fq, fr = ti.field(ti.f32, shape=(E, *cells)), ti.field(ti.u8, shape=(E, *cells))
    fq.from_numpy(q.astype(np.float32))
    fr.from_numpy(region.astype(np.uint8))
    content = fq.to_numpy().astype(np.float64) * 0.5
    axes = tuple(range(1, len(cells) + 1))
    sums = MemberSums(grid, E, sets)
    rec = sums.record(fq, 0.5, fr)
    assert np.allclose(rec["mass"], content.sum(axis=axes), rtol=1e-12)
    assert np.array_equal(rec["negative_cells"], (content < 0).sum(axis=axes))
    assert np.allclose(rec["particles"], np.where(region, content, 0).sum(axis=axes), rtol=1e-12)
    assert np.array_equal(rec["region_cells"], region.sum(axis=axes))
    for name, m in sets.items():
        assert np.allclose(rec[name], content[:, m].sum(axis=1), rtol=1e-12)
    plain = MemberSums(grid, E, {}).record(fq, 0.5)  # no region, no sets
    assert set(plain) == {"mass", "negative_cells"} and np.array_equal(plain["mass"], rec["mass"])


def test_scalars_are_read_together_as_they_are():
    a, b, c = ti.field(ti.f64, shape=()), ti.field(ti.f32, shape=()), ti.field(ti.i64, shape=())
    a[None], b[None], c[None] = 1 / 3, 0.1, 2**52 + 1
    scalars = Scalars([a, b, c])
    values = scalars.read()  # on the CPU: read one by one
    assert values[0] == a[None] and values[1] == b[None] and values[2] == 2**52 + 1  # exact
    scalars._pack()  # a GPU's path: one kernel packs them (the class must be data-oriented for it)
    assert np.array_equal(scalars.out.to_numpy(), values)
