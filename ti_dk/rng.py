"""Counter-based random numbers: Philox-4x32-10 and a one-uniform → one-normal transform.

Every random number is a pure function of (seed, counter), with the counter built from
(index, step, ensemble member, purpose). Results therefore do not depend on the thread count,
the launch order or the backend, unlike ``ti.random``.

References: Salmon et al., "Parallel random numbers: as easy as 1, 2, 3" (SC'11) for Philox;
P. J. Acklam's rational approximation of the inverse normal CDF (relative error < 1.15e-9).
"""

import taichi as ti

# purposes: the fourth counter word, so that streams for different uses never overlap
FACE_NOISE = 0  # one counter per group of 4 // dim cells along the last axis; word g·dim + a: lower face along a of cell g
WALK = 1  # one counter per group of 4 // dim particle ids and step; word (id0 mod G)·dim + a: step along a
SAMPLE_COUNT = 2  # Bernoulli draw for the fractional particle of a cell
SAMPLE_POSITION = 3  # uniform position of a sampled particle
PURPOSE_BITS = 4  # the purpose occupies the low bits of word 3; the rest is free for callers

_M0, _M1 = 0xD2511F53, 0xCD9E8D57
_W0, _W1 = 0x9E3779B9, 0xBB67AE85


def seed_key(seed: int) -> tuple[int, int]:
    """Split a 64-bit seed into the two 32-bit Philox key words."""
    return seed & 0xFFFFFFFF, (seed >> 32) & 0xFFFFFFFF


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


@ti.func
def normal(bits: ti.u32, T: ti.template()):
    """A standard normal number of type ``T`` from one 32-bit word (Acklam's inverse CDF).

    The top bit gives the sign and the low 31 bits a probability p ∈ (0, ½), so both tails reach
    |z| ≈ 6.4 symmetrically and no precision is lost near p = 1.
    """
    # signed integer → float conversion is one instruction; unsigned is several on x86
    p = (T(ti.cast(bits & ti.u32(0x7FFFFFFF), ti.i32)) + T(0.5)) * T(2.0**-32)
    z = T(0.0)
    if p < T(0.02425):
        r = ti.sqrt(T(-2.0) * ti.log(p))
        num = ((((T(-7.784894002430293e-03) * r + T(-3.223964580411365e-01)) * r + T(-2.400758277161838e00)) * r
                + T(-2.549732539343734e00)) * r + T(4.374664141464968e00)) * r + T(2.938163982698783e00)
        den = (((T(7.784695709041462e-03) * r + T(3.224671290700398e-01)) * r + T(2.445134137142996e00)) * r
               + T(3.754408661907416e00)) * r + T(1.0)
        z = num / den
    else:
        s = p - T(0.5)
        r = s * s
        num = (((((T(-3.969683028665376e01) * r + T(2.209460984245205e02)) * r + T(-2.759285104469687e02)) * r
                 + T(1.383577518672690e02)) * r + T(-3.066479806614716e01)) * r + T(2.506628277459239e00)) * s
        den = ((((T(-5.447609879822406e01) * r + T(1.615858368580409e02)) * r + T(-1.556989798598866e02)) * r
                + T(6.680131188771972e01)) * r + T(-1.328068155288572e01)) * r + T(1.0)
        z = num / den
    if bits & ti.u32(0x80000000):
        z = -z
    return z
