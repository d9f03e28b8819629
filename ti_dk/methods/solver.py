"""The solver contract: what the run controller asks of every method's solver, with defaults for
what only some solvers have (a split of their step's time, regrids, a particle region)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np


@dataclass(frozen=True)
class Snapshot:
    """One member as an openPMD snapshot shows it (:func:`ti_dk.output.files.write_openpmd`)."""

    density: np.ndarray  # number density [1/volume], (*cells)
    region: np.ndarray | None = None  # booleans, (*cells): the particle region, for solvers that have one
    positions: np.ndarray | None = None  # (particles, dim) [length]: the particles of that region
    pid: np.ndarray | None = None  # (particles, 2) u32: each particle's (slot at birth, birth step + 1)
    boxes: np.ndarray | None = None  # (boxes, 2 dim) i64: lo (one per axis), hi (exclusive), in cells


class Solver:
    """Base of every method's solver: ``step``, ``density``, ``diagnostics``, ``state`` and
    ``load_state`` are its own; the rest has a default here that a solver may override.

    Solvers are built and initialised by :func:`ti_dk.make_solver`, so ``initialize`` is
    no part of the contract (its arguments differ between methods).
    """

    timing: Mapping[str, float] = MappingProxyType({})  # seconds per part of the step, if the solver splits it
    regrids: Sequence[dict] = ()  # one record per regrid of a particle region
    boxes: Sequence[list] = ()  # per member: the boxes ((lo, …), (hi, …)) in cells of its particle region

    def step(self, n: int) -> None:
        """Advance every member from step ``n`` to ``n + 1``."""
        raise NotImplementedError

    def density(self) -> np.ndarray:
        """Number density [1/volume] of every member, ``(ensemble, *cells)``."""
        raise NotImplementedError

    def diagnostics(self) -> dict[str, float]:
        """Sums over all members after the last step: at least ``mass`` (particles)."""
        raise NotImplementedError

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume the solver exactly (a checkpoint's content)."""
        raise NotImplementedError

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """Resume from what :meth:`state` returned."""
        raise NotImplementedError

    def region(self) -> np.ndarray | None:
        """The particle region of every member, ``(ensemble, *cells)`` booleans; None without one."""
        return None

    def content(self) -> tuple:
        """On the device, what :meth:`density` reads: its field ``(ensemble, *cells)`` (filled: any
        kernel it needs has run), the factor that makes it particles per cell, and the particle
        region's u8 field (None without one): for sums on the device (:mod:`.records`)."""
        raise NotImplementedError

    def snapshot(self, member: int = 0) -> Snapshot:
        """Member ``member`` as its openPMD snapshot shows it: its density."""
        return Snapshot(density=self.density()[member])


class RegionSolver(Solver):
    """A solver with particles in a region of each member (the hybrid): its snapshot adds the
    region, those particles and the region's boxes. ``state()`` holds the particles as ``x``
    ``(ensemble, slots, dim)``, ``pid`` ``(ensemble, slots, 2)`` and ``n_real`` ``(ensemble,)``."""

    def region(self) -> np.ndarray:
        """The particle region of every member, booleans ``(ensemble, *cells)``."""
        raise NotImplementedError

    def snapshot(self, member: int = 0) -> Snapshot:
        """Member ``member``: its density, region, the region's particles and its boxes."""
        region = self.region()[member]
        st = self.state()
        k = int(st["n_real"][member])
        boxes = np.array([(*lo, *hi) for lo, hi in self.boxes[member]], dtype=np.int64).reshape(-1, 2 * region.ndim)
        return Snapshot(self.density()[member], region, st["x"][member, :k], st["pid"][member, :k], boxes)
