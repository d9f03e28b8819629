"""Streaming per-cell statistics: central moments to 4th order, one-particle-wide histograms and the
structure factor S(k) of the counts."""
from __future__ import annotations

import numpy as np

from .spectra import half_shape


class Moments:
    """Per-cell count, mean and central sums ``M_p = Σ (x − mean)^p`` for p = 2, 3, 4, in float64.

    Batches are merged with the pairwise update of Pébay (2008, SAND2008-6212, eq. 2.1–2.3),
    so ensembles, time samples and (later) distributed chunks combine exactly.
    """

    def __init__(self, shape: tuple[int, ...]):
        self.n = 0
        self.mean = np.zeros(shape)
        self.m2 = np.zeros(shape)
        self.m3 = np.zeros(shape)
        self.m4 = np.zeros(shape)

    def add(self, x: np.ndarray) -> None:
        """Add the samples ``x[k, ...]`` (first axis: samples)."""
        x = np.asarray(x, dtype=np.float64)
        other = Moments(self.mean.shape)
        other.n = x.shape[0]
        other.mean = x.mean(axis=0)
        d = x - other.mean
        d2 = d * d
        other.m2 = d2.sum(axis=0)
        other.m3 = (d2 * d).sum(axis=0)
        other.m4 = (d2 * d2).sum(axis=0)
        self.merge(other)

    def merge(self, o: "Moments") -> None:
        """Combine with another accumulator (Pébay's pairwise formulas)."""
        na, nb = self.n, o.n
        if nb == 0:
            return
        if na == 0:
            self.n, self.mean, self.m2, self.m3, self.m4 = nb, o.mean.copy(), o.m2.copy(), o.m3.copy(), o.m4.copy()
            return
        n = na + nb
        delta = o.mean - self.mean
        d2 = delta * delta
        m4 = (self.m4 + o.m4 + d2 * d2 * na * nb * (na * na - na * nb + nb * nb) / n**3
              + 6.0 * d2 * (na * na * o.m2 + nb * nb * self.m2) / n**2 + 4.0 * delta * (na * o.m3 - nb * self.m3) / n)
        m3 = self.m3 + o.m3 + d2 * delta * na * nb * (na - nb) / n**2 + 3.0 * delta * (na * o.m2 - nb * self.m2) / n
        self.m2 = self.m2 + o.m2 + d2 * na * nb / n
        self.m3, self.m4 = m3, m4
        self.mean = self.mean + delta * nb / n
        self.n = n

    def state(self) -> dict[str, np.ndarray]:
        """The accumulator as arrays (for checkpoints and merging rows)."""
        return {"n": np.int64(self.n), "mean": self.mean, "m2": self.m2, "m3": self.m3, "m4": self.m4}

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """Continue from a :meth:`state`."""
        self.n, self.mean, self.m2, self.m3, self.m4 = int(st["n"]), st["mean"], st["m2"], st["m3"], st["m4"]

    @property
    def variance(self) -> np.ndarray:
        """Unbiased sample variance, M2 / (n − 1)."""
        return self.m2 / (self.n - 1) if self.n > 1 else np.zeros_like(self.m2)

    @property
    def skewness(self) -> np.ndarray:
        """√n M3 / M2^{3/2} (NaN where a cell never varied)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.sqrt(self.n) * self.m3 / self.m2**1.5

    @property
    def kurtosis(self) -> np.ndarray:
        """Non-excess kurtosis n M4 / M2² (3 for a Gaussian, as in the paper's Fig. 3)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.n * self.m4 / self.m2**2


class Histogram:
    """Per-cell counts of the particle number ``k = round(q V_c)`` in bins ``lo … hi``, one
    particle wide (bin k covers [(k − ½)/V_c, (k + ½)/V_c), the paper's Fig. 2); values outside
    are counted in ``outside``."""

    def __init__(self, shape: tuple[int, ...], lo: int, hi: int):
        self.lo, self.hi = lo, hi
        self.counts = np.zeros((*shape, hi - lo + 1), dtype=np.int64)
        self.outside = np.zeros(shape, dtype=np.int64)

    def add(self, particles: np.ndarray) -> None:
        """Add samples ``particles[k, ...]`` given in particles per cell."""
        k = np.rint(particles).astype(np.int64) - self.lo
        nb = self.hi - self.lo + 1
        inside = (k >= 0) & (k < nb)
        cell = np.broadcast_to(np.arange(self.outside.size).reshape(self.outside.shape), k.shape)
        flat = cell[inside] * nb + k[inside]
        self.counts += np.bincount(flat, minlength=self.counts.size).reshape(self.counts.shape)
        self.outside += (~inside).sum(axis=0)


class StructureFactor:
    """Streaming S(k) over samples of the number density (the definition: :mod:`ti_dk.core.spectra`)."""

    def __init__(self, cells: tuple[int, ...], cell_volume: float):
        self.cells = tuple(cells)
        self.cell_volume = cell_volume  # V_c: density → particle count
        self.moments = Moments((2, *half_shape(self.cells)))  # real and imaginary parts of N̂_k

    def add(self, density: np.ndarray) -> None:
        """Add samples of the number density, shaped ``(samples, *cells)``."""
        counts = np.asarray(density, dtype=np.float64) * self.cell_volume
        nk = np.fft.rfftn(counts, axes=tuple(range(1, counts.ndim)))
        self.moments.add(np.stack([nk.real, nk.imag], axis=1))

    def value(self) -> np.ndarray:
        """S(k) on the kept modes (NaN with no particles on average; 0 with fewer than 2 samples)."""
        total = self.moments.mean[(0,) * self.moments.mean.ndim]  # ⟨N̂_0⟩ = ⟨N_total⟩
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.moments.variance.sum(axis=0) / total


class CellStats:
    """Moments (number density), optional histogram (particles per cell) and optional structure
    factor (:class:`StructureFactor`) for one output row."""

    def __init__(self, shape: tuple[int, ...], cell_volume: float, histogram: tuple[int, int] | None = None,
                 structure_factor: bool = False):
        self.cell_volume = cell_volume
        self.moments = Moments(shape)
        self.histogram = Histogram(shape, *histogram) if histogram else None
        self.spectrum = StructureFactor(shape, cell_volume) if structure_factor else None  # S(k), or None

    def add(self, density: np.ndarray) -> None:
        """Add samples of the number density, shaped ``(samples, *cells)``."""
        self.moments.add(density)
        if self.histogram is not None:
            self.histogram.add(density * self.cell_volume)
        if self.spectrum is not None:
            self.spectrum.add(density)

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume accumulating (for checkpoints)."""
        st = self.moments.state()
        if self.histogram is not None:
            st |= {"hist_counts": self.histogram.counts, "hist_outside": self.histogram.outside}
        if self.spectrum is not None:
            st |= {f"sf_{k}": v for k, v in self.spectrum.moments.state().items()}
        return st

    def load_state(self, st: dict[str, np.ndarray]) -> None:
        """Continue from a :meth:`state`."""
        self.moments.load_state(st)
        if self.histogram is not None:
            self.histogram.counts, self.histogram.outside = st["hist_counts"], st["hist_outside"]
        if self.spectrum is not None:
            self.spectrum.moments.load_state({k[3:]: v for k, v in st.items() if k.startswith("sf_")})

    def row(self) -> dict[str, np.ndarray]:
        """The statistics row so far: the four moments per cell, the sample count, the histogram and
        S(k) where kept, and the accumulators (``acc_*``) that :meth:`merge_row` adds."""
        m = self.moments
        row = {"mean": m.mean, "variance": m.variance, "skewness": m.skewness, "kurtosis": m.kurtosis,
               "n_samples": np.int64(m.n)}
        if self.histogram is not None:
            row["histogram"] = self.histogram.counts
            row["histogram_outside"] = self.histogram.outside
        if self.spectrum is not None:
            row["structure_factor"] = self.spectrum.value()
        return row | {f"acc_{k}": v for k, v in self.state().items()}  # to merge rows of member chunks

    def merge_row(self, row: dict[str, np.ndarray]) -> None:
        """Add the accumulators carried by another row (Pébay merge; histograms add)."""
        other = CellStats(self.moments.mean.shape, self.cell_volume,
                          (self.histogram.lo, self.histogram.hi) if self.histogram else None, self.spectrum is not None)
        other.load_state({k[4:]: v for k, v in row.items() if k.startswith("acc_")})
        self.moments.merge(other.moments)
        if self.histogram is not None:
            self.histogram.counts = self.histogram.counts + other.histogram.counts
            self.histogram.outside = self.histogram.outside + other.histogram.outside
        if self.spectrum is not None:
            self.spectrum.moments.merge(other.spectrum.moments)
