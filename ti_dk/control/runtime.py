"""What every run shares: Taichi's start-up and the result types (stop signals and the errors: :mod:`.signals`)."""
from __future__ import annotations

import contextlib
import ctypes
import io
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import taichi as ti

from ..core.errors import ConfigError
from ..scene.schema import Scene

ARCHS = {"cpu": ti.cpu, "cuda": ti.cuda}  # the backends a run may ask for, by their --arch name


def init(arch: str = "cpu", threads: int | None = None) -> None:
    """Start Taichi on ``arch`` ('cpu' or 'cuda'); refuse a backend that is absent or unsupported.

    Literals in kernels are f64 (``default_fp``); solvers cast them to their own precision.
    """
    if arch not in ARCHS:
        raise ConfigError(f"backend '{arch}' is not supported: use --arch cpu or --arch cuda")
    if threads is not None and threads < 1:
        raise ConfigError(f"threads = {threads}: give at least 1 CPU thread")
    if arch == "cuda" and not cuda_driver_present():
        raise ConfigError("the 'cuda' backend is not available on this machine (no CUDA driver): run with --arch cpu")
    _keep_freed_memory()
    _plain_source_positions()
    kw = {"cpu_max_num_threads": threads} if threads else {}
    with contextlib.redirect_stdout(io.StringIO()):  # ti.init prints "[Taichi] Starting on arch=..." unasked
        ti.init(arch=ARCHS[arch], default_fp=ti.f64, offline_cache=True, log_level=ti.WARN, **kw)
    _STARTED["thread"] = threading.get_ident()
    if ti.lang.impl.current_cfg().arch != ARCHS[arch]:
        raise ConfigError(f"the '{arch}' backend is not available on this machine: run with --arch cpu")


_STARTED = {"thread": None}  # the thread that started Taichi through init (None: not started by ti_dk)


def started_here() -> bool:
    """Whether Taichi may run on this thread: it was started on it (by :func:`init`), or not by
    ti_dk (then nothing is known), or not at all.

    Taichi's LLVM backend works only on the thread that started it. Symptom of a run on another:
    ``RuntimeError: [llvm_context.cpp:add_struct_module] Assertion failure: this_thread ==
    main_thread``, and with two such runs at once the process dies (SIGSEGV or SIGABRT)."""
    return _STARTED["thread"] in (None, threading.get_ident()) or not initialized()


def started_by_this_thread() -> bool:
    """Whether :func:`init` started Taichi on this very thread."""
    return _STARTED["thread"] == threading.get_ident() and initialized()


def _keep_freed_memory() -> None:
    """Let glibc's malloc keep the memory of freed large arrays for the next ones.

    A regrid makes a dozen grid-sized host arrays (the density, tags, masks, the slot estimate:
    megabytes each in 3D). By default glibc maps each afresh and unmaps it when freed, so every
    one is paid again in page faults, which on virtual machines are slow and erratic (the same
    work took ten times longer one time than the next). With no mmap below 1 GiB and no trimming,
    freed memory stays in the process and is reused.
    Only where the C library is glibc (``mallopt`` exists); elsewhere nothing changes."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 1 << 30)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, 2**31 - 1)  # M_TRIM_THRESHOLD (a C int)
    except (OSError, AttributeError):
        pass


def _plain_source_positions() -> None:
    """Make Taichi's compiler label each statement with its file and line only.

    Taichi 1.7.4's AST transformer (``ASTTransformerContext.get_pos_info``) formats, for every
    statement and expression of every kernel it builds, the source line with a caret line under
    the node, both wrapped to 80 columns by ``textwrap``, even when nothing fails and the kernel
    then comes from the offline cache (the frontend runs on every start). Symptom: a start-up with
    a warm kernel cache spends about a second in ``get_pos_info`` (``textwrap`` is the largest
    Python cost of the start-up). A compilation error still names the
    file, line and kernel."""
    from taichi.lang.ast import ast_transformer_utils as utils

    def file_and_line(ctx, node) -> str:
        return f'File "{ctx.file}", line {node.lineno + ctx.lineno_offset}, in {ctx.func.func.__name__}:\n'

    utils.ASTTransformerContext.get_pos_info = file_and_line


def cuda_driver_present() -> bool:
    """Whether this machine has a CUDA driver (Taichi would otherwise fall back to the CPU silently)."""
    try:
        ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    return True


def initialized() -> bool:
    """Whether Taichi has been started in this process."""
    return ti.lang.impl.get_runtime().prog is not None


@dataclass(frozen=True)
class Stats:
    """Per-row, per-cell statistics of a run: one row per output time (one pooled row for a
    stationary run), over the ensemble's members (and time samples).

    Attributes
    ----------
    mean : numpy.ndarray
        ``(rows, *cells)``, number density [particles / L^d]; times ``cell_volume`` gives
        particles per cell.
    variance : numpy.ndarray
        ``(rows, *cells)`` [1 / L^(2d)].
    skewness : numpy.ndarray
        ``(rows, *cells)``, dimensionless.
    kurtosis : numpy.ndarray
        ``(rows, *cells)``, kurtosis, not excess (3 for a Gaussian, as in the paper's Fig. 3), dimensionless.
    n_samples : numpy.ndarray
        ``(rows,)``: densities pooled into each row (members × time samples).
    histogram : numpy.ndarray or None
        ``(rows, *cells, bins)``: counts of particles per cell in one-particle bins from
        ``hist_lo`` (only with the scene key ``histogram``).
    hist_lo : int or None
        The particle count of the first histogram bin.
    """

    mean: np.ndarray  # (rows, *cells) [1/volume]
    variance: np.ndarray  # (rows, *cells) [1/volume²]
    skewness: np.ndarray  # (rows, *cells), dimensionless
    kurtosis: np.ndarray  # (rows, *cells), non-excess (3 for a Gaussian: Moments.kurtosis), dimensionless
    n_samples: np.ndarray  # (rows,) densities pooled into each row (members × time samples)
    histogram: np.ndarray | None = None  # particles per cell, bins hist_lo … (one particle wide)
    hist_lo: int | None = None  # the particle count of the first histogram bin
    structure_factor: np.ndarray | None = None  # (rows, *half cells) S(k), dimensionless (ti_dk.core.spectra)


def stats_of(rows: list[dict], hist: tuple[int, int] | None) -> Stats:
    """The rows stacked along time."""
    stack = {k: np.stack([r[k] for r in rows]) for k in rows[0] if not k.startswith("acc_")}
    return Stats(mean=stack["mean"], variance=stack["variance"], skewness=stack["skewness"],
                 kurtosis=stack["kurtosis"], n_samples=stack["n_samples"], histogram=stack.get("histogram"),
                 hist_lo=hist[0] if hist else None, structure_factor=stack.get("structure_factor"))


@dataclass(frozen=True)
class Result:
    """What :func:`ti_dk.run` returns: its statistics, per-step diagnostics, final densities and
    where its files are. Densities are number densities (particles per unit volume, L^-d); times
    in L²/(2D) (D = ½).

    Attributes
    ----------
    scene : Scene
        The scene that ran (validated, with every default filled in).
    times : numpy.ndarray
        The time of each statistics row, ``(rows,)``.
    cell_volume : float
        V_c [L^d]: multiply a density by it for particles per cell.
    stats : Stats
        Per-cell mean, variance, skewness, kurtosis (3 for a Gaussian) at each row, ``(rows, *cells)``.
    diagnostics : dict of str to numpy.ndarray
        Per step, summed or taken over all members: ``time``, ``mass`` (particles),
        ``min_density``, ``negative_cells``, ``clamped_steps``, ``boundary_inflow``; the hybrid
        adds ``particles`` and ``regrid_change``, a compared method ``compare_*``.
    final_density : numpy.ndarray
        Every member's density at the end, ``(ensemble, *cells)``.
    wall_time : float
        Seconds the run took.
    regrids : list of dict
        Hybrid: one record per regrid (``step``, ``boxes``, ``covered_cells``, ``efficiency``,
        ``created``, ``removed``, ``on_demand``), as in ``/regrid`` of the run file.
    timing : dict of str to float
        Seconds per part of the run (setup, compile, regrid, spde, particles, statistics, …).
    frames : list of pathlib.Path
        The PNG frames written.
    written : dict of str to pathlib.Path
        Every file or folder written, by what it holds.
    rows : list of dict
        The statistics rows with their moment accumulators (to merge ensembles exactly).
    series : dict of str to numpy.ndarray
        Per member, every ``scene.observe_every`` steps (step 0 and the last too): ``time``
        ``(records,)``; ``mass``, ``negative_cells`` (the hybrid: ``particles``, ``region_cells``)
        and each ``[observables]`` region's particle count, ``(records, members)``.
    chunks : dict
        Distributed runs: the chunk count and the chunks that were retried.
    path : pathlib.Path or None
        The run file (``OUT/<name>_<method>.h5``), if one was written.
    samples : list of numpy.ndarray or None
        With ``run(samples=True)``: per row, every member's density behind it,
        ``(samples per member, ensemble, *cells)`` (a stationary row pools several steps).
    """

    scene: Scene  # the scene that ran
    times: np.ndarray  # the time of each statistics row
    cell_volume: float  # V_c, to turn number densities into particles per cell
    stats: Stats  # the statistics rows
    diagnostics: dict[str, np.ndarray] = field(repr=False)  # per step: mass, negative cells, … (all members)
    final_density: np.ndarray = field(repr=False)  # every member at the end, (ensemble, *cells)
    wall_time: float = 0.0  # seconds the run took
    regrids: list[dict] = field(default_factory=list, repr=False)  # hybrid: one record per regrid
    timing: dict[str, float] = field(default_factory=dict)  # seconds per part of the run
    frames: list[Path] = field(default_factory=list)  # PNG frames written
    written: dict[str, Path] = field(default_factory=dict)  # every file or folder written, by what it holds
    rows: list[dict] = field(default_factory=list, repr=False)  # statistics rows with their accumulators
    series: dict[str, np.ndarray] = field(default_factory=dict, repr=False)  # per member, over time
    chunks: dict = field(default_factory=dict)  # distributed runs: chunk count and the retried chunks
    path: Path | None = None  # the run file, if one was written
    samples: list[np.ndarray] | None = field(default=None, repr=False)  # run(samples=True): each row's densities
