"""One Taichi runtime for the whole test process (kernels compile once per solver object).

Under pytest-xdist every worker, and every process a worker's tests start, gets an offline
kernel cache of its own (``<cache>-<worker>``): two processes dumping into one cache at exit
contend for its lock ("Lock .../ticache.lock failed" on stderr, measured), and a test reading a
child's stderr must see only what ti_dk writes."""
import os

import pytest
import taichi as ti

import ti_dk

_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    _base = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH") or ti.lang.impl.default_cfg().offline_cache_file_path
    os.environ["TI_OFFLINE_CACHE_FILE_PATH"] = f"{_base.rstrip('/')}-{_WORKER}"


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    ti_dk.init("cpu")
