"""A natural logarithm over arrays that LLVM vectorises (numba has no vector libm here).

``log_pass(x, out, n)`` sets ``out[:n] = ln(x[:n])``. For a positive normal x = m * 2^e with
m in [sqrt(1/2), sqrt(2)) (read off the bits, exact), f = m - 1 (exact) and s = f / (2 + f):

    ln(m) = 2 atanh(s) = f - s * (f - T),   T = sum_{k=1..10} 2 s^(2k) / (2k + 1)

(since 2s = f - f s), with |s| <= 0.1716, so the series' 11th term is below 1e-18 of ln(m);
ln(x) = e * LN2_HI + (ln(m) + e * LN2_LO), where LN2_HI has 42 significant bits (e * LN2_HI
is exact) and LN2_LO = ln 2 - LN2_HI. Error <= 1 ulp against libm (tested); ln(1) = 0 exactly.
The loop is branch-free; elements that are not positive normal numbers (0, subnormal, inf,
NaN, negative) are counted and recomputed afterwards by libm, so they behave as ``np.log``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from evchain.kernels.intrinsics import float_bits, from_bits

#: ln 2 rounded to a multiple of 2^-42, and the rest (derived with 60-digit decimal arithmetic)
LN2_HI = 0.6931471805598903
LN2_LO = 5.497923018708371e-14
#: bits of sqrt(1/2) (rounded up): x's bits minus these give e in the exponent field
_SQRT_HALF_BITS = 0x3FE6A09E667F3BCD
_MANT = 0x000FFFFFFFFFFFFF
_MIN_NORMAL_BITS = 0x0010000000000000
#: bits of +inf minus those of the smallest normal: the width of the positive normal range
_NORMAL_SPAN = 0x7FE0000000000000


@njit(cache=True, inline="always", error_model="numpy")
def _ln(x):
    """(ln x, 1) for a positive normal float64 x; (garbage, 0) otherwise. Branch-free."""
    b = float_bits(x)
    ok = np.int64(np.uint64(b - _MIN_NORMAL_BITS) < np.uint64(_NORMAL_SPAN))
    e = (b - _SQRT_HALF_BITS) >> 52                   # arithmetic shift: e of m in range
    m = from_bits(b - (e << 52))
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    t = z * (2 / 3 + z * (2 / 5 + z * (2 / 7 + z * (2 / 9 + z * (2 / 11 + z * (
        2 / 13 + z * (2 / 15 + z * (2 / 17 + z * (2 / 19 + z * (2 / 21))))))))))
    de = np.float64(e)
    return de * LN2_HI + ((f - s * (f - t)) + de * LN2_LO), ok


@njit(cache=True, error_model="numpy")
def ln(x):
    """ln(x) of one float64, the same value as ``log_pass`` gives (libm where x is not a
    positive normal number)."""
    v, ok = _ln(x)
    return v if ok else np.log(x)


@njit(cache=True, error_model="numpy")
def log_pass(x, out, n):
    """``out[k] = ln(x[k])`` for k < n (float64 1-D arrays); as ``np.log`` to <= 1 ulp."""
    nok = np.int64(0)
    for k in range(np.uint64(n)):
        v, ok = _ln(x[k])
        out[k] = v
        nok += ok
    if nok != n:
        for k in range(n):
            if not _ln(x[k])[1]:
                out[k] = np.log(x[k])
