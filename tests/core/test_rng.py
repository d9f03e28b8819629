"""Philox known answers, and the moments and tails of the generated normals against N(0, 1)."""
import math

import numpy as np
import pytest
import taichi as ti

from ti_dk.core import rng

KAT = [  # Random123 kat_vectors: counter[4], key[2] -> output[4]
    ([0, 0, 0, 0, 0, 0], [0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8]),
    ([0xFFFFFFFF] * 6, [0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD]),
    ([0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344, 0xA4093822, 0x299F31D0],
     [0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1]),
]


def test_philox_known_answers():
    inp = ti.field(ti.u32, shape=(3, 6))
    out = ti.field(ti.u32, shape=(3, 4))

    @ti.kernel
    def kat():
        for j in range(3):
            r = rng.philox4x32(ti.math.uvec4(inp[j, 0], inp[j, 1], inp[j, 2], inp[j, 3]),
                               ti.math.uvec2(inp[j, 4], inp[j, 5]))
            for w in ti.static(range(4)):
                out[j, w] = r[w]

    inp.from_numpy(np.array([k[0] for k in KAT], dtype=np.uint32))
    kat()
    assert out.to_numpy().tolist() == [k[1] for k in KAT]


N = 1 << 22


def _draw(real, kind):
    rng.prepare()
    f = ti.field(real, shape=N)

    @ti.kernel
    def fill(seed: ti.u32):
        for i in range(N // 4):
            r = rng.philox4x32(ti.math.uvec4(ti.u32(i), 0, 0, 0), ti.math.uvec2(seed, 0))
            for w in ti.static(range(4)):
                if ti.static(kind == "normal"):
                    f[4 * i + w] = rng.normal(r[w], real)
                else:
                    f[4 * i + w] = rng.uniform(r[w], real)

    fill(12345)
    return f.to_numpy().astype(np.float64)


@pytest.mark.parametrize("real", [ti.f32, ti.f64], ids=["f32", "f64"])
def test_normal_moments_and_tails(real):
    z = _draw(real, "normal")
    n = len(z)
    # moments to 4th order against N(0,1); standard errors are those of the estimators
    assert abs(z.mean()) < 5 * math.sqrt(1 / n)
    assert abs(z.var() - 1) < 5 * math.sqrt(2 / n)
    assert abs((z**3).mean()) < 5 * math.sqrt(15 / n)
    assert abs((z**4).mean() - 3) < 5 * math.sqrt(96 / n)
    # tails: P(|Z| > a) = erfc(a / √2), binomial sampling error
    for a in (1.0, 2.0, 3.0, 4.0, 4.5):
        p = math.erfc(a / math.sqrt(2))
        frac = np.mean(np.abs(z) > a)
        assert abs(frac - p) < 5 * math.sqrt(p * (1 - p) / n) + 1 / n, (a, frac, p)
    # symmetric and finite, reaching beyond 5 sigma but bounded by the 31-bit resolution
    assert np.isfinite(z).all() and 4.8 < np.abs(z).max() < 6.5
    assert abs(np.mean(z > 0) - 0.5) < 5 * math.sqrt(0.25 / n)


@pytest.mark.parametrize("real", [ti.f32, ti.f64], ids=["f32", "f64"])
def test_uniform_is_open_interval_and_flat(real):
    u = _draw(real, "uniform")
    assert 0 < u.min() and u.max() < 1
    hist = np.histogram(u, bins=64, range=(0, 1))[0]
    expected = len(u) / 64
    chi2 = ((hist - expected) ** 2 / expected).sum()
    assert chi2 < 63 + 6 * math.sqrt(2 * 63)


@pytest.mark.parametrize("real, tol", [(ti.f32, 2e-6), (ti.f64, 2e-9)], ids=["f32", "f64"])
def test_normal_is_the_inverse_cdf_of_its_word(real, tol):
    """Every octave and segment of the table (and Acklam's deep tail) against statistics.NormalDist:
    the word ``w`` must give Φ⁻¹((m + ½) 2⁻³²), m = w & 0x7FFFFFFF, negated when the top bit is set."""
    from statistics import NormalDist
    gen = np.random.default_rng(0)
    m = np.concatenate([np.arange(0, 1 << 10),  # the deep tail and the first table octaves
                        (2 ** gen.uniform(10, 31, 1 << 16)).astype(np.int64),  # all octaves
                        [2**31 - 1, 2**30, 2**30 - 1, 2**24, 2**24 - 1]]).clip(0, 2**31 - 1)
    words = np.concatenate([m, m | (1 << 31)]).astype(np.uint32)
    rng.prepare()
    w = ti.field(ti.u32, shape=words.size)
    z = ti.field(real, shape=words.size)
    w.from_numpy(words)

    @ti.kernel
    def fill():
        for i in w:
            z[i] = rng.normal(w[i], real)

    fill()
    inv = NormalDist().inv_cdf
    exact = np.array([inv((v + 0.5) * 2.0**-32) for v in m])
    exact = np.concatenate([exact, -exact])
    got = z.to_numpy().astype(np.float64)
    assert np.max(np.abs(got - exact) / np.maximum(1, np.abs(exact))) < tol
