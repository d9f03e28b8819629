"""One Taichi runtime for the whole test process (kernels compile once per solver object).

Under pytest-xdist every worker, and every process a worker's tests start, gets an offline
kernel cache of its own (``<cache>-<worker>``): two processes dumping into one cache at exit
contend for its lock ("Lock .../ticache.lock failed" on stderr, measured), and a test reading a
child's stderr must see only what ti_dk writes. A worker runs Taichi on one thread."""
import os
import time
from pathlib import Path

import pytest
import taichi as ti

import ti_dk

_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    _base = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH") or ti.lang.impl.default_cfg().offline_cache_file_path
    os.environ["TI_OFFLINE_CACHE_FILE_PATH"] = f"{_base.rstrip('/')}-{_WORKER}"
    # Taichi 1.7.4 locks its offline cache with a file that a killed process leaves behind; every later
    # process then prints "Lock .../ticache.lock failed" on stderr at start and exit (which tests that
    # read stderr see) and never updates the cache. A dump takes seconds: a lock older than ten
    # minutes is stale.
    _lock = Path(os.environ["TI_OFFLINE_CACHE_FILE_PATH"]) / "ticache.lock"
    if _lock.exists() and time.time() - _lock.stat().st_mtime > 600:
        _lock.unlink(missing_ok=True)


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    # one thread per xdist worker: the workers already fill the cores, and two threads each made
    # four on two cores (tests/hybrid + tests/control, warm cache: 2:33 → 2:16 wall, CPU −13 %).
    # Tests of thread counts start processes of their own (helpers.digest_on_threads).
    ti_dk.init("cpu", threads=1 if _WORKER else None)
