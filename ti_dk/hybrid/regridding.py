"""Regrids of the AMAR hybrid (paper §3.2): a scheduled regrid (tag, buffer, tiles or
Berger–Rigoutsos), the on-demand extension, and moving the particles to a new region."""

import math

import numpy as np

from . import clustering

# one record per regrid; on_demand: members regridded off schedule (0: a scheduled regrid of all)
REGRID_LOG = ("step", "boxes", "covered_cells", "efficiency", "created", "removed", "on_demand")


class Regridding:
    """The regrid half of :class:`~.solver.HybridSolver` (whose state it reads and sets)."""

    def regrid(self, n: int) -> None:
        """New region from the SPDE density at step ``n``: tiles flagged on the device, with
        hysteresis (:meth:`_retile`), or tag, buffer, Berger–Rigoutsos on the host."""
        if self.regions.tiles is not None:
            self._retile(n, self.params.release * self.params.threshold, False)
            return
        ppc = self._content()
        masks, tagged = self.regions.plan(ppc)
        self._set_region(masks, n, ppc, sort=True)
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
        """
        if self.regions.tiles is not None:
            self._retile(n, math.inf, True)
            return
        ppc = self._content()
        tags = clustering.tag(ppc, self.params.threshold)  # once: the extension and its log's count
        masks, members = self.regions.plan_extension(tags)
        self._set_region(masks, n, ppc)
        self._log(n, int(tags.sum()), members)

    def _retile(self, n: int, keep: float, extending: bool) -> None:
        """A region of tiles flagged on the device (:meth:`Region.plan_tiles`; ``keep``: a covered
        tile stays while a cell near it holds less). Members whose region is unchanged (with
        hysteresis, most at most regrids) cost nothing more: where none changed, nothing
        grid-sized is read or written, and no particle moves (the order of the particles in a pool
        changes no result, so the scheduled regrid's sort is skipped too)."""
        masks, tagged = self.regions.plan_tiles(self.spde, keep)
        changed = (masks != self.regions.mask()).reshape(self.ensemble, -1).any(axis=1)
        if changed.any():
            self._set_region(masks, n, self._content(), sort=not extending)
        else:
            self._removed, self._created = 0.0, 0
        self._log(n, tagged, int(changed.sum()) if extending else 0)

    def _content(self) -> np.ndarray:
        """The SPDE content of every cell, ``q V_c`` (particles per cell, float64), scaled in place:
        :meth:`SPDESolver.density` returns a fresh array, so a regrid makes one grid-sized array
        here, not two."""
        ppc = self.spde.density()
        ppc *= self.grid.cell_volume
        return ppc

    def _log(self, n: int, tagged: int, on_demand: int) -> None:
        """One record of :data:`REGRID_LOG`; ``efficiency`` is ``tagged`` over the covered cells, all
        members: a scheduled regrid's tags after the buffer, an extension's cells below
        ``threshold`` before it (kept so: the pinned run files hold both)."""
        covered = self.n_cover
        self.regrids.append({"step": n, "boxes": self.regions.box_count(), "covered_cells": covered,
                             "efficiency": tagged / covered if covered else 1.0,
                             "created": self._created, "removed": self._removed,
                             "on_demand": on_demand})

    def set_region(self, masks: np.ndarray, n: int) -> None:
        """Make ``masks`` (``(ensemble, *cells)`` booleans) the particle region at step ``n``, its
        diagnostics up to date (a region set from outside, between steps)."""
        self._set_region(masks, n, self._content())
        self.diagnose()

    def _set_region(self, masks: np.ndarray, n: int, ppc: np.ndarray, sort: bool = False) -> None:
        """:meth:`set_region` inside a step (regrid, extension), where the step's own
        synchronisation brings the diagnostics up to date: no full-grid pass here. With ``sort``
        (the scheduled regrids) the kept particles are put in cell order (:meth:`Coupling.sort`).
        Between steps every particle lies in a covered cell, so a region that only grows keeps
        them all where they are (:meth:`pools.ParticlePool.settle`; a compaction would copy every
        particle at every extension)."""
        masks = np.broadcast_to(masks, (self.ensemble, *self.n))
        old = self.regions.mask()
        grown = self.regions.grown(masks)
        near = grown | old  # where particles can be while the region moves: old, new, ring
        self.pool = self.pool.fitted(self._estimate(masks, near, ppc), near)
        sort = sort and not self.pool.cell_ordered
        cells, n_new, n_gone = self.regions.stage(masks)
        # the SPDE content the newly covered cells held, summed here: the same bits on any thread count
        self._removed = float(ppc.reshape(-1)[cells[:n_new]].sum())
        self.sampler.cover(self.pool, self.cur, n * self.substeps, self._tilt_on(n), self.coupling.count,
                           cells, n_new, n_gone, int(sort or n_gone > 0))
        self._created = int(self.sampler.created[None])
        if sort:
            self.coupling.sort(self.pool, self.cur)
            self.cur = 1 - self.cur
        elif n_gone:
            self._compact()
        else:  # the region only grew (every extension): no particle leaves, a compaction would copy them all
            self.pool.settle(self.cur)
        self.pool.retain(grown)  # the new region and its ring
        self.regions.lists(grown)
        if self.sampler.check_need() > self.pool.capacity:  # the estimate bounds it; kept as a guard
            raise RuntimeError("particle pool estimate too small at a regrid")
        self._change += self._created - self._removed

    def _estimate(self, masks: np.ndarray, near: np.ndarray, ppc: np.ndarray) -> np.ndarray:
        """Slots each cell can ask for around a regrid (``(ensemble, *cells)``; the pool adds the
        headroom of :func:`pools.capacity`): the region and its ghost ring full, and a covered
        cell's reservoir ghosts."""
        need = np.maximum(ppc, 0)  # in place from here: one grid-sized array per regrid, not three
        need *= near
        np.ceil(need, out=need)
        if self.grid.has_dirichlet:
            need += self.grid.reservoir_ppc_max * 3 ** (self.dim - 1) * masks
        return need
