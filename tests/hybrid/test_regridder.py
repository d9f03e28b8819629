"""The hybrid's regrids (:class:`~ti_dk.hybrid.regridder.Regridder`): the scheduled regrid's cell
order, the regrid ledger and a region that follows the density, the on-demand extension and its
hysteresis, positivity with both."""
import numpy as np
import pytest

from ti_dk import load_scene
from ti_dk.control.registry import make_solver
from ti_dk.core.traffic import counted
from ti_dk.hybrid import clustering
from ti_dk.scene.estimates import hybrid_slots

from ..helpers import covered_nonnegative, run_steps


def _solver(scene):
    return make_solver(scene, scene.initial_ppc)


def _low(s, trigger):
    """The uncovered cells of hybrid ``s`` holding fewer than ``trigger`` particles (Region.count_low)."""
    s.regions.count_low(s.spde, trigger, False)
    return s.regions.low[None]


@pytest.mark.parametrize("cells", [[30, 26], [10, 12, 8]])
def test_scheduled_regrid_sorts_the_particles_by_cell(cells):
    # a scheduled regrid of boxes leaves each member's particles of a flat pool in cell order (Coupling.sort),
    # every particle in a covered cell and as many in each as the cell's density says (tiles skip the sort
    # where no member's region changed: Regridder._retile)
    scene = load_scene("ellipse2d", method="hybrid", cells=cells, regrid_interval=3, ensemble=2, ppc_outer=12,
                       ppc_inner=6, threshold=4.0, seed=6, region="boxes") if len(cells) == 2 else \
        load_scene("void1d", method="hybrid", cells=cells, regrid_interval=3, ensemble=2, ppc=8, seed=6,
                   region="boxes")
    s = _solver(scene)
    for n in range(5):
        s.step(n)
    s.regrid(5)
    x, n_real = s.pool.x.to_numpy()[s.cur], s.pool.n.to_numpy()[s.cur]  # slot order (occupied() sorts by id)
    q, region = s.density() * s.grid.cell_volume, s.region()
    for e in range(2):
        cell = np.minimum((x[e, :n_real[e]] / s.grid.dx).astype(int), np.array(cells) - 1)
        flat = np.ravel_multi_index(tuple(cell.T), tuple(cells))
        assert n_real[e] > 0 and np.all(np.diff(flat) >= 0)
        counts = np.bincount(flat, minlength=np.prod(cells)).reshape(cells)
        assert np.all(region[e][counts > 0])
        assert np.array_equal(counts[region[e]], np.round(q[e][region[e]]).astype(int))


@pytest.mark.parametrize("kind", ["tiles", "boxes"])
def test_a_region_from_the_mean_is_every_members_and_q_bars(kind):
    # region_from = "mean" (the default): the members' densities differ after a few steps, their regions
    # do not; the region is q̄'s tags, grown by the buffer, covered by tiles or clustered once as boxes
    # (the tag, grow and cluster functions run on q̄'s content); each member's own would differ
    scene = load_scene("ellipse2d", method="hybrid", cells=[32, 24], regrid_interval=4, ensemble=3, ppc_outer=8,
                       ppc_inner=4, threshold=5.0, seed=2, region=kind, region_from="mean", regrid_floor=0)
    assert (clustering.RegridParams().region_from, clustering.RegridParams().regrid_floor) == ("mean", 0)
    s = _solver(scene)
    for n in range(7):
        s.step(n)
    s.regrid(7)
    region, vol = s.region(), s.grid.cell_volume
    assert all(np.array_equal(region[0], region[e]) for e in (1, 2)) and 0 < region[0].mean() < 1
    mean = s.spde.qbar.to_numpy()[0].astype(float) * vol
    tags = clustering.grow(clustering.tag(mean, 5.0)[None], 1, (None, True, True))[0]
    assert np.all(region[0][tags])  # every grown tag covered: by whole tiles, or by boxes
    if kind == "boxes":
        want, _ = clustering.region(mean, scene.hybrid.regrid, (True, True), {})[1:]
        assert np.array_equal(region[0], want)
    own = [np.array_equal(clustering.region(q, scene.hybrid.regrid, (True, True), {})[1], region[0])
           for q in s.density() * vol]
    assert not all(own)


def test_regrid_ledger_and_region_follows_density():
    # 2D ellipses: the empty ring is tagged; as it fills cells leave the region and, as the inner
    # ellipse empties, new cells enter it
    scene = load_scene("ellipse2d", method="hybrid", cells=[40, 40], regrid_interval=4, ppc_outer=12,
                       ppc_inner=6, threshold=4.0, t_end=0.01, seed=5)
    s = _solver(scene)
    start = s.region()
    ever, left = start.copy(), np.zeros_like(start)

    def track(s):
        covered_nonnegative(s)
        r = s.region()
        assert np.array_equal(r, s.regions.covered.to_numpy() != 0)  # the host's copy is the device's mask
        left[...] |= start & ~r
        ever[...] |= r

    h = run_steps(s, 120, track)
    mass, change = h["mass"], h["regrid_change"]
    # exact ledger: the only change of the total is what regrids created minus what they removed
    assert np.allclose(np.diff(mass), change[1:], rtol=0, atol=1e-9 * mass[0])
    assert any(change[1:])
    assert left.sum() > 20 and (ever & ~start).sum() > 20
    log = s.regrids
    assert [r["step"] for r in log if not r["on_demand"]] == list(range(0, 120, 4))
    assert all(r["step"] % 4 for r in log if r["on_demand"])
    assert sum(r["created"] - r["removed"] for r in log[1:]) == pytest.approx(change.sum(), abs=1e-9)


@pytest.mark.slow  # 200 members, 88 steps with regrids
def test_composite_stays_positive_with_regridding():
    # 200 members of a small ellipse2d: without the on-demand regrid, uncovered cells next to the
    # region drift below a particle between scheduled regrids and can go negative
    scene = load_scene("ellipse2d", cells=[48, 48], ensemble=200, compare="none", seed=4)
    s = _solver(scene)
    h = run_steps(s, scene.n_steps, covered_nonnegative)
    assert h["negative_cells"].max() == 0 and h["min_density"].min() >= 0
    assert np.allclose(np.diff(h["mass"]), h["regrid_change"][1:], rtol=0, atol=1e-9 * h["mass"][0])


def test_regrid_on_demand():
    # a region kept for 1000 steps cannot follow an emptying ellipse: the cells that fall below
    # the threshold are covered on demand, before the step, and the rest of the region is kept
    scene = load_scene("ellipse2d", method="hybrid", cells=[40, 40], regrid_interval=1000, ppc_outer=12,
                       ppc_inner=6, threshold=4.0, t_end=0.01, seed=5, region_from="member", regrid_floor=0.6)
    s = _solver(scene)
    start = s.region()
    vol = s.grid.cell_volume
    for n in range(60):
        before = s.region()
        s.step(n)
        if n > 0 and s.regrids[-1]["step"] == n:  # extended at the start of this step
            assert s.regrids[-1]["on_demand"] == 1 and np.all(s.region() >= before)
        assert s.diagnostics()["negative_cells"] == 0
    demand = [r for r in s.regrids if r["on_demand"]]
    assert len(demand) > 3 and (s.region() & ~start).sum() > 20
    # an extension, where one is due, leaves no uncovered cell below the threshold (with tiles, which
    # cover whole tiles around the low cells, none was due at step 60 of this run)
    if _low(s, 4.0) > 0:
        s.extend(60)
    q = s.density() * vol
    assert q[~s.region()].min() >= 4.0
    # hysteresis: with regrid_floor = 0.5 an extension is due below 2 particles but covers
    # everything below 4, so it comes less often; no uncovered cell is below 2 after it
    half = _solver(scene.replace(regrid_floor=0.5))
    for n in range(60):
        half.step(n)
    assert 0 < sum(r["on_demand"] > 0 for r in half.regrids) < len(demand)
    if _low(half, 2.0):  # due before step 60
        half.extend(60)
    q = half.density() * vol
    assert q[~half.region()].min() >= 2.0
    # from q̄, an extension covers only the cells below the trigger (their tiles): fewer cells
    least = _solver(scene.replace(regrid_floor=0.5, region_from="mean"))
    for n in range(60):
        least.step(n)
    assert sum(r["on_demand"] > 0 for r in least.regrids) > 0
    if _low(least, 2.0):
        least.extend(60)
    q = least.density() * vol
    assert q[~least.region()].min() >= 2.0 and q[~least.region()].min() < 4.0
    assert least.region().sum() < half.region().sum()


@pytest.mark.parametrize("region_from", ["mean", "member"])
def test_a_step_reads_back_a_few_counts(region_from):
    # every host touch of the device counted (core.traffic): a step without a regrid reads the fill's
    # slot count, and the end-of-step low-cell count only where an extension can be (regrid_floor > 0),
    # and writes nothing; a regrid reads the flag's three counts, and where the region changed the
    # move's sums (Tally), the sampler's two counts and the lists' lengths: never the flags or the
    # density; over the run, at most 64 bytes a step on average. The pool was planned before the run
    # (estimates.hybrid_slots, or more for a first region that needs more) and never grows: a new pool
    # would compile the kernels that take it anew
    scene = load_scene("ellipse2d", cells=[48, 48], compare="none", seed=4, region_from=region_from,
                       regrid_floor=0.6 if region_from == "member" else 0)
    s = _solver(scene)
    pool = s.pool
    rows = []
    with counted() as t:
        for n in range(150):
            before = len(s.regrids)
            t.reset()
            s.step(n)
            rows.append((len(s.regrids) > before, t.read, t.written))
    regrid, read, written = np.array(rows).T
    assert regrid.sum() > 10 and len({r["covered_cells"] for r in s.regrids}) >= 3  # the region moved
    assert read[regrid == 0].max() == (12 if region_from == "member" else 8) and written[regrid == 0].max() == 0
    assert read.max() <= 96 and written.max() == 0  # a few counts (76 bytes): nothing grid- or tile-sized
    assert read.mean() <= 64
    assert s.pool is pool and pool.capacity >= hybrid_slots(scene)
