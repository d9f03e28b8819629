"""One Taichi runtime for the whole test process (kernels compile once per solver object)."""
import numpy as np
import pytest

import ti_dk


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    ti_dk.init("cpu")


def sampling_se(pmf: np.ndarray, members: int, replicas: int = 400, seed: int = 0) -> dict[str, float]:
    """Standard errors of the sample mean, variance, skewness and kurtosis of ``members`` draws from
    an exact PMF on 0, 1, 2, …, found by drawing ``replicas`` independent ensembles from it."""
    rng = np.random.default_rng(seed)
    x = rng.choice(len(pmf), size=(replicas, members), p=pmf / pmf.sum()).astype(float)
    m = x.mean(axis=1, keepdims=True)
    d = x - m
    m2 = (d**2).mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        skew = (d**3).mean(axis=1) / m2**1.5
        kurt = (d**4).mean(axis=1) / m2**2
    return {"mean": x.mean(axis=1).std(), "variance": x.var(axis=1, ddof=1).std(),
            "skewness": np.nanstd(skew), "kurtosis": np.nanstd(kurt)}
