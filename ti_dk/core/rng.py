"""Counter-based random numbers: Philox-4x32-10 and a one-word → one-normal transform.

Every random number is a pure function of (seed, counter), with the counter built from
(index, step, ensemble member, purpose). Results therefore do not depend on the thread count,
the launch order or the backend, unlike ``ti.random``.

The normal is the inverse normal CDF of the word, by table: the word's 31 low bits fall in one
of 23 octaves, each cut into 32 segments on which Φ⁻¹ is a cubic (absolute error < 1e-9, fitted
at import of the table from :class:`statistics.NormalDist`); the deepest tail (p < 2⁻²⁴, one word
in 2²³) uses Acklam's tail formula. The table costs a load and three multiply-adds where Acklam's
rational approximation takes two degree-5 polynomials and a division.

References: Salmon et al., "Parallel random numbers: as easy as 1, 2, 3" (SC'11) for Philox;
P. J. Acklam's rational approximation of the inverse normal CDF (relative error < 1.15e-9).
"""
import functools
from statistics import NormalDist

import numpy as np
import taichi as ti

# purposes: the fourth counter word, so that streams for different uses never overlap
FACE_NOISE = 0  # one counter per group of 4 // dim cells along the last axis; word g·dim + a: lower face along a of cell g
WALK = 1  # one counter per group of 4 // dim particle ids and step; word (id0 mod G)·dim + a: step along a
SAMPLE_COUNT = 2  # Bernoulli draw for the fractional particle of a cell
SAMPLE_POSITION = 3  # uniform position of a sampled particle
SAMPLE_ENTRY = 4  # a ghost drawn as one that enters the region (hybrid.crossings.Crossings.entrant); attempt t in the free bits
PURPOSE_BITS = 4  # the purpose occupies the low bits of word 3; the rest is free for callers

_OCT0 = 8  # octaves m < 2**_OCT0 of the 31-bit magnitude (p < 2**-24) use Acklam's tail formula
_SEG = 5  # 2**_SEG cubic segments per octave
_TABLE: dict = {}  # the Taichi program the tables belong to, and the tables (one per precision)

_M0, _M1 = 0xD2511F53, 0xCD9E8D57
_W0, _W1 = 0x9E3779B9, 0xBB67AE85


def seed_key(seed: int) -> tuple[int, int]:
    """Split a 64-bit seed into the two 32-bit Philox key words.

    Each word is returned as the signed 32-bit integer with the same bits: kernels bake the key in
    as Python literals, which Taichi types as i32 (a word >= 2**31 failed to compile with "exceeded
    the range of default_ip: i32") and ``ti.math.uvec2`` casts back to the same unsigned bits.
    Seeds below 2**31 give exactly the words they always gave.
    """
    if not 0 <= seed < 2**64:
        raise ValueError(f"seed {seed} is outside [0, 2**64)")
    return tuple(w - 2**32 if w >= 2**31 else w for w in (seed & 0xFFFFFFFF, seed >> 32))


def lanes(dim: int, flux: bool = False, alone: bool = False) -> int:
    """Philox calls one iteration of a walk or (``flux``) flux loop makes before it uses them, in
    ``dim`` dimensions: 2 in 3D, where a counter serves one particle or cell, and 1 in 1D and 2D,
    where it already serves 2–4, except the 2D flux loop and a walk whose particles each make
    their own call (``alone``: the hybrid's, whose slots are not in identity order): 2. A call is
    a chain of dependent multiplies, so with one at a time the loop waits on it, and two
    independent ones run side by side in the core. That pays in 3D (walk and flux pass), in the
    2D flux loop, which goes along rows, and in the hybrid's 2D walk (8 % of that kernel,
    benchmarks/RESULTS.md); elsewhere in 1D and 2D it gains nothing or loses, and every lane is
    a copy of the loop body to compile."""
    return 2 if dim == 3 or (dim == 2 and (flux or alone)) else 1


def device_key(key: tuple[int, int], member0: int = 0) -> ti.Field:
    """The key as a field of unsigned words, which kernels read at run time (``key[0]``,
    ``key[1]``, as they read a tuple of literals: the same bits), and in its third word the global
    index of the solver's member 0 (:func:`member_word`).

    A key of literals is baked into every kernel that draws, so the offline cache compiles them
    all anew for each seed: a warm cache of the same scene with another seed cost sphere3d at 64³
    13.4 s of compilation in its first step instead of 2.0. Read from a
    field, one compiled kernel serves every seed, and every chunk of an ensemble (``member0``).
    Solvers built by :func:`ti_dk.make_solver` get this form.
    """
    f = ti.field(ti.u32, shape=3)  # the two Philox key words of the run, then the first member's global index
    f.from_numpy(np.array([w & 0xFFFFFFFF for w in (*key, member0)], dtype=np.uint32))
    return f


@ti.func
def member_word(key: ti.template(), member0: ti.template(), e):
    """The counter word of local member ``e``: its global index ``member0 + e`` (mod 2³²), read from
    the third word of a :func:`device_key` field, or from ``member0`` where ``key`` is a tuple of
    literals (then baked in)."""
    out = ti.u32(0)
    if ti.static(isinstance(key, tuple)):
        out = ti.u32(e + member0)
    else:
        out = ti.u32(e) + key[2]
    return out


@ti.func
def _mulhilo(m: ti.u64, a: ti.u32) -> ti.math.uvec2:
    p = m * ti.cast(a, ti.u64)
    return ti.math.uvec2(ti.cast(p >> 32, ti.u32), ti.cast(p & ti.u64(0xFFFFFFFF), ti.u32))


@ti.func
def philox4x32(ctr: ti.math.uvec4, key: ti.math.uvec2) -> ti.math.uvec4:
    """Philox-4x32-10 (Random123): four independent uniform 32-bit words per counter."""
    c = ctr
    k = key
    for _ in ti.static(range(10)):
        p0 = _mulhilo(ti.u64(_M0), c[0])
        p1 = _mulhilo(ti.u64(_M1), c[2])
        c = ti.math.uvec4(p1[0] ^ c[1] ^ k[0], p1[1], p0[0] ^ c[3] ^ k[1], p0[1])
        k = k + ti.math.uvec2(ti.u32(_W0), ti.u32(_W1))
    return c


@ti.func
def uniform(bits: ti.u32, T: ti.template()):
    """A uniform number in the open interval (0, 1) of type ``T`` (23 bits for f32, 32 for f64)."""
    u = T(0.0)
    if ti.static(T == ti.f32):
        u = (T(ti.cast(bits >> 9, ti.i32)) + T(0.5)) * T(2.0**-23)  # 1 - 2**-24 is the largest f32 below 1
    else:
        u = (T(ti.cast(bits, ti.i64)) + T(0.5)) * T(2.0**-32)
    return u


@functools.cache
def inverse_cdf_table() -> np.ndarray:
    """Cubic coefficients ``(c0, c1, c2, c3)`` of Φ⁻¹ on every segment, ``(octaves · 2^SEG, 4)``.

    Octave ``j`` (``_OCT0 ≤ j ≤ 30``) holds the magnitudes ``m ∈ [2^j, 2^{j+1})``, segment ``s`` of
    it ``m + ½ = m0 + t·w``, ``w = 2^{j−SEG}``, ``t ∈ (0, 1)``; the cubic fits ``Φ⁻¹((m0 + t w) 2⁻³²)``
    in ``t`` at six Chebyshev nodes (least squares).
    """
    inv = NormalDist().inv_cdf
    nodes = 0.5 - 0.5 * np.cos((2 * np.arange(6) + 1) * np.pi / 12)
    rows = []
    for j in range(_OCT0, 31):
        w = 2 ** (j - _SEG)
        for seg in range(2**_SEG):
            m0 = 2**j + seg * w
            z = [inv((m0 + t * w) / 2**32) for t in nodes]  # t = 0 is m0 + ½, the first magnitude's p
            rows.append(np.polyfit(nodes, z, 3)[::-1])
    return np.array(rows)


def prepare() -> None:
    """Create the normal tables of the running Taichi program (call after ``ti.init``, before
    compiling a kernel that draws normals; solvers do it in their constructors)."""
    prog = ti.lang.impl.get_runtime().prog
    if _TABLE.get("prog") is not prog:
        coef = inverse_cdf_table()
        _TABLE.clear()
        _TABLE["prog"] = prog
        for T in (ti.f32, ti.f64):
            f = ti.Vector.field(4, T, shape=coef.shape[0])  # cubic coefficients of Φ⁻¹ per segment
            f.from_numpy(coef.astype(np.float32 if T == ti.f32 else np.float64))
            _TABLE[T] = f


def _table(T):
    if _TABLE.get("prog") is not ti.lang.impl.get_runtime().prog:
        raise RuntimeError("rng.prepare() must be called after ti.init and before kernels that draw normals")
    return _TABLE[T]


@ti.func
def _power_of_two(k, T: ti.template()):
    """2^-k for 0 ≤ k < 126 as type ``T``, built from its exponent bits."""
    v = T(0.0)
    if ti.static(T == ti.f32):
        v = ti.bit_cast(ti.cast((127 - k) << 23, ti.i32), ti.f32)
    else:
        v = ti.bit_cast(ti.cast(1023 - k, ti.i64) << 52, ti.f64)
    return v


@ti.func
def normal(bits: ti.u32, T: ti.template()):
    """A standard normal number of type ``T`` from one 32-bit word (inverse CDF by table).

    The top bit gives the sign and the low 31 bits ``m`` a probability ``p = (m + ½) 2⁻³²`` in
    (0, ½), so both tails reach |z| ≈ 6.4 symmetrically and no precision is lost near p = 1.
    """
    m = ti.cast(bits & ti.u32(0x7FFFFFFF), ti.i32)
    z = T(0.0)
    if m < (1 << _OCT0):  # p < 2^-24: Acklam's tail (one word in 2^23)
        p = (T(m) + T(0.5)) * T(2.0**-32)
        r = ti.sqrt(T(-2.0) * ti.log(p))
        num = ((((T(-7.784894002430293e-03) * r + T(-3.223964580411365e-01)) * r + T(-2.400758277161838e00)) * r
                + T(-2.549732539343734e00)) * r + T(4.374664141464968e00)) * r + T(2.938163982698783e00)
        den = (((T(7.784695709041462e-03) * r + T(3.224671290700398e-01)) * r + T(2.445134137142996e00)) * r
               + T(3.754408661907416e00)) * r + T(1.0)
        z = num / den
    else:
        j = 31 - ti.math.clz(m)  # the octave: 2^j ≤ m < 2^(j+1)
        sh = j - _SEG
        c = ti.static(_table(T))[((j - _OCT0) << _SEG) | ((m >> sh) & ((1 << _SEG) - 1))]
        t = (T(m & ((1 << sh) - 1)) + T(0.5)) * _power_of_two(sh, T)
        z = c[0] + t * (c[1] + t * (c[2] + t * c[3]))
    if bits & ti.u32(0x80000000):
        z = -z
    return z
