"""The rules every pool follows (``ti_dk/pools/slots.py``): the members' total and the one capacity
rule against Poisson fluctuations."""
import math

import numpy as np
import pytest
import taichi as ti

from ti_dk import pools


@pytest.mark.parametrize("E", [3, 40])  # read one by one, and copied at once
def test_total_sums_a_row_of_member_counts(E):
    counts = ti.field(ti.i32, shape=(2, E))
    values = np.random.default_rng(E).integers(0, 2**30, size=(2, E), dtype=np.int32)
    counts.from_numpy(values)
    assert pools.total(counts, (1,)) == values[1].sum(dtype=np.int64)
    assert pools.total(counts, (0,)) == values[0].sum(dtype=np.int64)


def test_capacity_rule_holds_poisson_fluctuations():
    for need in (0, 1, 10, 1e3, 1e6):
        c = pools.capacity(need)
        assert c >= need + 4 * math.sqrt(need) + 64 and c <= 1.5 * need + 4 * math.sqrt(need) + 64
