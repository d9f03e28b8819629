"""Applications of ti_dk, apart from the library: the paper's figures and the speed/accuracy trade.

Run from the repository root (``python -m studies.figures fig2``, ``python -m studies.tradeoff``);
the package is not installed with ti_dk. Each study runs its scenes through :func:`ti_dk.run`,
which writes one HDF5 file per run, and draws from what it reads back from those files.
"""
