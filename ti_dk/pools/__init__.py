"""Particle storage shared by the particle method and the hybrid: slots per member, growth,
one compaction per layout and one capacity rule.

Two layouts (scene key ``pool_layout``; the hybrid takes either, the particle method the flat one):

- :class:`ParticlePool` (``flat``): one array of slots per member, sized for the member's whole
  region; memory follows the particles of the busiest member.
- :class:`BlockPool` (``pointer``): a ``ti.root.pointer`` over blocks of cells, each active block
  holding its slots in dense chunks; only the blocks of the region and its ghost ring are active,
  so memory follows the region's particles, not the grid or the busiest member. Particles move
  between blocks by per-block counts and an exclusive scan (no ``dynamic`` appends, which
  contend: ``benchmarks/bench_pool.py``). Slower per step on 2 CPU cores, smaller in memory.

The hybrid reaches a particle through the same ti.funcs in both: a loop over :meth:`units`
(a member's chunk of slots, or a block), :meth:`unit` (its member, key and slot range),
:meth:`new_units` / :meth:`new_unit` (the same for the slots appended since the last compaction),
:meth:`split_unit` (a unit's slots cut into the held and the appended),
:meth:`index` (the index of a slot in ``x``, ``pid``), :meth:`unit_of` and :meth:`append` (room
for new particles of a cell), :meth:`mark` / :meth:`marked` / :meth:`unmark` (whether a slot
survives the next :meth:`compacted`). A particle's random numbers are keyed on its ``pid``, never
on its slot, so both layouts give the same bits; :meth:`occupied` returns the particles sorted
by identity, so checkpoints are the same too.

Modules: :mod:`.slots` (the shared rules: slot counts, capacity, checkpoint order), :mod:`.flat`,
:mod:`.blocks` (made of three parts, each an object of its own: :mod:`.block_grid`,
:mod:`.block_memory` and :mod:`.block_moves`).
"""

from ..core.grid import light
from .blocks import BlockPool
from .flat import ParticlePool
from .slots import BLOCK, LAYOUTS, canonical, capacity, total

__all__ = ["BLOCK", "LAYOUTS", "BlockPool", "ParticlePool", "canonical", "capacity", "make", "total"]


def make(layout: str, grid, ensemble: int, real):
    """An empty hybrid pool of ``layout`` (one of :data:`LAYOUTS`) for ``grid``."""
    if layout == "pointer":
        return BlockPool(grid, ensemble, 1, real)
    return ParticlePool(ensemble, 1, grid.dim, real, light=light(grid.dim))
