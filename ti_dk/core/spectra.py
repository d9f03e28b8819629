"""The static structure factor S(k) of the density fluctuations, accumulated over an ensemble.

Definition (the one :mod:`ti_dk.core.theory` answers exactly): with ``N_j = q_j V_c`` the
particle count of cell j at ``x_j`` and ``δN_j = N_j − ⟨N_j⟩``,

    S(k) = ⟨|Σ_j δN_j e^{−i k·x_j}|²⟩ / ⟨N_total⟩,

per wave number of the grid, ``k_a = 2π m_a / L_a``. Independent particles at uniform equilibrium
give S = 1 for k ≠ 0 (0 at k = 0 where the total is conserved); the linear FV scheme gives
``1/(1 − Δt λ(k)/4)`` (:func:`ti_dk.core.theory.linear_structure_factor`). The counts are real, so
only numpy's ``rfftn`` half of the modes is kept (S(−k) = S(k)): the last axis holds
``m = 0 … M/2``. ⟨·⟩ is over the samples (members, and time samples in a pooled row): the real
and imaginary parts of ``N̂_k = Σ_j N_j e^{−i k·x_j}`` are accumulated with
:class:`ti_dk.core.stats.Moments` (in :class:`ti_dk.core.stats.StructureFactor`), so ``⟨|δN̂_k|²⟩`` is their summed unbiased variance and
⟨N_total⟩ the mean of ``N̂_0``; accumulators merge exactly across chunks (Pébay).

Sampling error of one row from n independent samples: ``|δN̂_k|²`` is near exponential (the sum
of many particles' phases), so the estimate's relative standard error is ``1/√n``; a *real* mode
(``m_a ∈ {0, M_a/2}`` on every axis, :func:`real_modes`) has one Gaussian part, a χ²₁ estimate,
and ``√(2/n)``. Successive time samples of one member are correlated (mode k decays by
``(1 − 2 s_k)²`` per step), so a pooled row's error is larger than its sample count says.
"""
from __future__ import annotations

import numpy as np


def half_shape(cells: tuple[int, ...]) -> tuple[int, ...]:
    """The shape of the modes kept: ``rfftn``'s half grid."""
    return (*cells[:-1], cells[-1] // 2 + 1)


def half(full: np.ndarray) -> np.ndarray:
    """The kept half of an array over the full DFT grid (numpy's FFT order), e.g. a theory."""
    return full[..., : full.shape[-1] // 2 + 1]


def wavenumbers(cells: tuple[int, ...], lengths: tuple[float, ...]) -> list[np.ndarray]:
    """``k_a = 2π m_a / L_a`` per axis in the kept half grid's order (last axis ``m ≥ 0`` only)."""
    ks = [2 * np.pi * np.fft.fftfreq(m, L / m) for m, L in zip(cells[:-1], lengths[:-1])]
    return ks + [2 * np.pi * np.fft.rfftfreq(cells[-1], lengths[-1] / cells[-1])]


def magnitude(cells: tuple[int, ...], lengths: tuple[float, ...]) -> np.ndarray:
    """``|k|`` of every kept mode."""
    return np.sqrt(sum(k**2 for k in np.meshgrid(*wavenumbers(cells, lengths), indexing="ij")))


def real_modes(cells: tuple[int, ...]) -> np.ndarray:
    """True where a kept mode equals its own conjugate (``2 m_a ≡ 0 mod M_a`` on every axis):
    its transform is real, and its estimate has twice the relative variance of the others."""
    m = np.meshgrid(*[np.arange(n) for n in half_shape(cells)], indexing="ij")
    return np.logical_and.reduce([(2 * mi) % n == 0 for mi, n in zip(m, cells)])


def independent_modes(cells: tuple[int, ...]) -> np.ndarray:
    """True on one mode of each conjugate pair the half grid holds twice (where ``2 m_last ≡ 0``,
    ``(m_0, …)`` and ``(−m_0, …)`` have the same estimate), so sums over it count every
    independent estimate once; k = 0 included."""
    m = np.meshgrid(*[np.arange(n) for n in half_shape(cells)], indexing="ij")
    keep = np.ones(half_shape(cells), dtype=bool)
    twice = (2 * m[-1]) % cells[-1] == 0
    undecided = twice.copy()  # the first leading axis where m ≠ −m decides which of the two is kept
    for mi, n in zip(m[:-1], cells[:-1]):
        conj = (-mi) % n
        keep &= ~(undecided & (mi > conj))
        undecided &= mi == conj
    return keep


def relative_se(cells: tuple[int, ...], samples: int) -> np.ndarray:
    """The relative standard error of S(k) from ``samples`` independent samples per kept mode:
    ``1/√n``, ``√(2/n)`` on real modes (module docstring)."""
    return np.where(real_modes(cells), np.sqrt(2.0 / samples), np.sqrt(1.0 / samples))
