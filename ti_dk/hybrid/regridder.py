"""The regrids of the AMAR hybrid (paper §3.2): :class:`Regridder`, the part of
:class:`~.solver.HybridSolver` that keeps the schedule, makes each new region (tiles on the device,
or tag, buffer and Berger–Rigoutsos on the host: :mod:`.clustering`), moves the particles to it,
and logs every regrid."""

import math

import numpy as np

from .. import pools
from . import clustering
from .tally import Tally

# one record per regrid; on_demand: members regridded off schedule (0: a scheduled regrid of all)
REGRID_LOG = ("step", "boxes", "covered_cells", "efficiency", "created", "removed", "on_demand")


class Regridder:
    """The regrids of ``solver`` (a :class:`~.solver.HybridSolver`: it reads the solver's SPDE, region,
    sampler and coupling, and sets its ``pool`` and ``cur`` when the particles move).

    The schedule (:meth:`when_due`): a regrid every ``interval`` steps (and at the start), and
    between them, for a member that starts a step with an uncovered cell below
    ``regrid_floor · threshold``, an extension (:meth:`extend`); ``interval = 0`` keeps the first
    region. A regrid tags and buffers, then flags tiles on the device with hysteresis
    (:mod:`.tiles`, the default) or runs Berger–Rigoutsos per member on the host
    (``region = "boxes"``); particles in cells that stay covered are kept, cells that leave the
    region keep their count as density, newly covered cells are sampled from the SPDE (the only
    step that changes the total; logged in :attr:`log`). At the start the state is the
    piecewise-constant initial condition, so those particles lie uniformly in their cells.

    Parameters
    ----------
    solver : HybridSolver
        The hybrid whose region this part moves.
    params : RegridParams
        The region's parameters (:class:`~.clustering.RegridParams`).
    interval : int
        Steps between scheduled regrids (0: the first region is kept, with no extension).
    """

    def __init__(self, solver, params: clustering.RegridParams, interval: int):
        self.solver, self.params, self.interval = solver, params, interval
        self.tally = Tally(solver.regions)  # a move's room and removed content, summed on the device
        self.log: list[dict] = []  # one record of REGRID_LOG per regrid
        self.change = 0.0  # created − removed at this step's regrid
        self._removed = 0.0  # SPDE content Σ q V_c of the cells the last regrid covered anew
        self._created = 0  # particles the last regrid sampled into them
        self._counted = False  # whether Region.low holds the count of q as it is now

    # -- the schedule -----------------------------------------------------------------------
    def when_due(self, n: int) -> None:
        """The first stage of step ``n``: the scheduled regrid every ``interval`` steps, else the
        extension where one is due (:meth:`count_low`); q changes after it, so the count is
        forgotten."""
        self.change = 0.0
        if self.interval and n > 0:
            if n % self.interval == 0:
                self.regrid(n)
            elif self.params.regrid_floor > 0 and self._extension_due():
                self.extend(n)
        self._counted = False  # q changes from here

    def count_low(self, diagnosing: bool = False) -> None:
        """Count on the device the uncovered cells holding fewer than ``regrid_floor · threshold``
        particles (:meth:`Region.count_low`; with ``diagnosing`` the SPDE's diagnostics in the same
        pass), for the next step's :meth:`when_due`."""
        s = self.solver
        s.regions.count_low(s.spde, self.params.trigger, diagnosing)
        self._counted = True

    def counted(self) -> None:
        """:meth:`count_low`'s count (and the diagnostics) made by the step's own launch
        (:meth:`Coupling.cross`)."""
        self._counted = True

    def _extension_due(self) -> bool:
        """Whether an uncovered cell holds fewer than ``regrid_floor · threshold`` particles (counted
        at the end of the last step, or now where that step was a plain SPDE step or a state was
        loaded): the one read of the count, made only where an extension can be."""
        if not self._counted:
            self.count_low()
        return self.solver.regions.low[None] > 0

    # -- the new region ---------------------------------------------------------------------
    def regrid(self, n: int) -> None:
        """New region from the SPDE density at step ``n`` (each member's own, or with ``region_from =
        "mean"`` the deterministic q̄'s, one region for every member): tiles flagged on the device,
        with hysteresis (:meth:`_retile`), or tag, buffer, Berger–Rigoutsos on the host."""
        s = self.solver
        p = self.params
        if s.regions.tiles is not None:
            self._retile(n, p.threshold, p.release * p.threshold, False)
            return
        ppc = self._content()
        masks, tagged = s.regions.plan(self._mean_content(ppc) if p.region_from == "mean" else ppc)
        self._move(masks, n, sort=True)
        self._log(n, tagged, 0)

    def extend(self, n: int) -> None:
        """Cover, before step ``n``, the uncovered cells below ``threshold`` (grown by the buffer,
        clustered by Berger–Rigoutsos; :meth:`Region.plan_extension`) and keep the rest of the
        region: the on-demand regrid, due when :meth:`Region.count_low` finds a cell below
        ``regrid_floor · threshold`` (:attr:`RegridParams.trigger`).

        Tagging promises that no uncovered cell holds fewer than ``threshold`` particles; between
        scheduled regrids that promise breaks, and FV then goes negative (one 2D step at C = 1/16
        moves about √N/2 particles). An extension is due when an uncovered cell holds fewer than
        ``regrid_floor · threshold``; it then covers every uncovered cell below ``threshold``, so
        the next one waits until a cell falls from above ``threshold`` to below the floor
        (hysteresis; with ``regrid_floor = 1`` the two sets are the same and an extension comes on
        most steps of ellipse2d). Together with the ghost-entry cap of :meth:`Coupling._cap`
        this cut the negative cell-steps of ellipse2d at threshold 5 from 47 to 1 (an FV step of
        4.7 σ from 5.6 particles); the cap alone to 8.

        With tiles, every tile that holds a cell below ``threshold`` after the buffer joins the
        region (:meth:`_retile`).

        With ``region_from = "mean"`` an extension covers only the member's cells below the trigger
        (grown by the buffer; with tiles, their tiles): the region the scheduled regrids take from
        q̄ is exact while it moves, and every cell an extension covers is chosen by the member's
        own noise, which biases the ensemble's means (``docs/hybrid.md``); covering the fewest keeps
        that bias as small as the protection allows.
        """
        s = self.solver
        p = self.params
        level = p.trigger if p.region_from == "mean" else p.threshold  # the cells an extension covers
        if s.regions.tiles is not None:
            self._retile(n, level, math.inf, True)
            return
        ppc = self._content()
        tags = clustering.tag(ppc, level)  # once: the extension and its log's count
        masks, members = s.regions.plan_extension(tags)
        self._move(masks, n)
        self._log(n, int(tags.sum()), members)

    def _retile(self, n: int, level: float, keep: float, extending: bool) -> None:
        """A region of tiles flagged on the device (:meth:`Region.plan_tiles`; ``level``: a tile holding a
        cell below it, grown by the buffer, is covered; ``keep``: a covered tile stays while a cell
        near it holds less). Members whose region is unchanged (with
        hysteresis, most at most regrids) cost nothing more: where none changed (counted on the
        device), two counts are read back, nothing else, and no particle moves (the order of the particles in a pool
        changes no result, so the scheduled regrid's sort is skipped too)."""
        s = self.solver
        mean = self.params.region_from == "mean" and not extending
        changed, tagged = s.regions.plan_tiles(s.spde, level, keep, mean, self.guard)
        members = 0  # members whose region changed
        if changed:
            s.regions.tiles.aim(self.tally.target)  # the flags' region, on the device
            members = self._move(None, n, sort=not extending)
        else:
            self._removed, self._created = 0.0, 0
        self._log(n, tagged, members if extending else 0)

    def _content(self) -> np.ndarray:
        """The SPDE content of every cell, ``q V_c`` (particles per cell, float64), scaled in place:
        :meth:`SPDESolver.density` returns a fresh array, so a regrid makes one grid-sized array
        here, not two."""
        ppc = self.solver.spde.density()
        ppc *= self.solver.grid.cell_volume
        return ppc

    @property
    def guard(self) -> float:
        """With ``region_from = "mean"``, a member's own cells below this join the region at every
        regrid (the trigger where extensions are on; −∞ where they are off)."""
        return self.params.trigger if self.params.regrid_floor > 0 else -math.inf

    def _mean_content(self, ppc: np.ndarray) -> np.ndarray:
        """What a regrid from q̄ tags boxes by: the content of the deterministic q̄ (eq. 10),
        ``q̄ V_c``, for every member, and −1 where the member's own content ``ppc`` is below
        :attr:`guard` (members with the same tags are clustered once, :meth:`Region.plan`)."""
        s = self.solver
        mean = s.spde.qbar.to_numpy().astype(np.float64) * s.grid.cell_volume
        return np.where(ppc < self.guard, -1.0, mean)

    def _log(self, n: int, tagged: int, on_demand: int) -> None:
        """One record of :data:`REGRID_LOG`; ``efficiency`` is ``tagged`` (the cells below
        ``threshold``, before the buffer) over the covered cells, all members: the share of the
        region that needs its particles, at every regrid and extension alike."""
        regions = self.solver.regions
        covered = regions.n_cover
        self.log.append({"step": n, "boxes": regions.box_count(), "covered_cells": covered,
                         "efficiency": tagged / covered if covered else 1.0,
                         "created": self._created, "removed": self._removed,
                         "on_demand": on_demand})

    # -- moving the particles ----------------------------------------------------------------
    def set_region(self, masks: np.ndarray, n: int) -> None:
        """Make ``masks`` (``(ensemble, *cells)`` booleans) the particle region at step ``n``, its
        diagnostics up to date (a region set from outside, between steps)."""
        self._move(masks, n)
        self.solver.diagnose()

    def _move(self, masks: np.ndarray | None, n: int, sort: bool = False) -> int:
        """:meth:`set_region` inside a step (regrid, extension), where the step's own
        synchronisation brings the diagnostics up to date: no full-grid pass here. ``masks``: the
        new region made on the host, or None where :attr:`Tally.target` holds it already (tiles:
        then nothing grid-sized crosses to the host, unless the pool plans its room by cell). With
        ``sort`` (the scheduled regrids) the kept particles are put in cell order
        (:meth:`Coupling.sort`). Between steps every particle lies in a covered cell, so a region
        that only grows keeps them all where they are (:meth:`pools.ParticlePool.settle`; a
        compaction would copy every particle at every extension). The pool's room, the content the
        new cells held, the cells uncovered and the members whose region moves are summed on the
        device (:class:`~.tally.Tally`); returns the last."""
        s = self.solver
        if masks is not None:
            masks = np.broadcast_to(masks, (s.ensemble, *s.n))
            self.tally.aim(masks)
        most, self._removed, gone, members = self.tally.count(s.spde)
        grown = None
        if s.pool.by_cell:  # its room planned, and kept, by cell: where particles can be while the region moves
            target = self.tally.target.to_numpy().astype(bool) if masks is None else masks
            grown = s.regions.grown(target)
            s.pool = s.pool.fitted(self.tally.per_cell(s.spde), grown | s.regions.mask())
        else:
            s.pool = s.pool.grown(pools.capacity(most), s.slots)
        sort = sort and not s.pool.cell_ordered
        s.sampler.cover(s.pool, s.cur, n * s.substeps, s.tilt_on(n), s.coupling.count, self.tally.target,
                        int(sort or gone > 0))
        self._created = int(s.sampler.created[None])
        if sort:
            s.coupling.sort(s.pool, s.cur)
            s.cur = 1 - s.cur
        elif gone:
            s.compact()
        else:  # the region only grew (every extension): no particle leaves, a compaction would copy them all
            s.pool.settle(s.cur)
        if grown is not None:
            s.pool.retain(grown)  # the new region and its ring
        s.regions.moved(masks)
        if s.sampler.check_need() > s.pool.capacity:  # the estimate bounds it; kept as a guard
            raise RuntimeError("particle pool estimate too small at a regrid")
        self.change += self._created - self._removed
        return members

    # -- checkpoints -------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """The log, one array per field of :data:`REGRID_LOG` (``regrid_<field>``)."""
        return {f"regrid_{k}": np.array([r[k] for r in self.log]) for k in REGRID_LOG}

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """The log from :meth:`state`'s arrays; the low cells are counted again when next asked."""
        self.log = [{k: st[f"regrid_{k}"][i].item() for k in REGRID_LOG} for i in range(len(st["regrid_step"]))]
        self._counted = False
