"""One Taichi runtime for the whole test process (kernels compile once per solver object)."""
import pytest

import ti_dk


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    ti_dk.init("cpu")
