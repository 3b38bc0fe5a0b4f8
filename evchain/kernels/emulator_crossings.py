"""Numba kernels of the DVS emulator's crossing times (the event loop in
:mod:`evchain.kernels.emulator`): where within a frame interval log intensity, interpolated
linearly or by a monotone cubic Hermite piece between the frames, reaches an event's level.
Newton runs over all crossings of an interval together (vectorised); the few whose checked step
fails are solved again by a safeguarded Newton with bisection.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from evchain.kernels.emulator_state import S_LAST

#: bound on the cubic crossing solve's error, in fractions of the frame interval
SOLVE_TOL = 1e-13
#: Newton steps run over all crossings of an interval together before the checked step
NEWTON_LOCKSTEP = 2


@njit(cache=True, inline="always", error_model="numpy")
def slope3(d1, d2, h1, h2):
    """Limited three-point slope at a node between secants d1 (width h1) and d2 (width h2).

    Exact for quadratics; zero at extrema; clipped to 3*min(|d1|, |d2|) (Fritsch-Carlson), so
    the cubic Hermite pieces on both sides stay monotone. Written as selects (no branches),
    so that a loop over pixels calling it has no branch to mispredict. (numpy error model, as
    in ``_interval``: no zero-divisor test per division; h1 + h2 > 0 as frame times
    increase.)
    """
    d = (h2 * d1 + h1 * d2) / (h1 + h2)
    a1 = abs(d1)
    a2 = abs(d2)
    m = 3.0 * (a1 if a1 < a2 else a2)     # min: NaN only where d is NaN too
    c = (m if d > 0 else -m) if abs(d) > m else d
    return 0.0 if d1 * d2 <= 0.0 else c


@njit(cache=True)
def solve_crossing(level, la, lb, m0, m1, cubic):
    """Fraction s in [0, 1] of the interval where the (monotone) piece reaches ``level``.

    Linear: (level - la) / (lb - la). Cubic: safeguarded Newton on the monotone Hermite piece
    in power form (Horner), started at the linear solution; bisection whenever Newton leaves
    the bracket. A Newton step d from s lands within (|p''(s)| d^2 / 2 + |p'''| |d|^3 / 6)
    / |p'(s)| of the root (Taylor), so it stops as soon as that bound is below ``SOLVE_TOL``
    (or the step below 1e-10), without a further step to confirm convergence. Levels outside
    [la, lb] clip to 0 or 1 (a level within the tie tolerance just beyond lb gives s = 1; a
    carried-over crossing gives 0).
    """
    if lb == la:
        return 0.0
    s = (level - la) / (lb - la)
    if s <= 0.0:
        return 0.0
    if s >= 1.0:
        return 1.0
    if not cubic:
        return s
    d = lb - la
    # p(s) - level = g + s (m0 + s (c2 + s c3))
    c2 = 3.0 * d - 2.0 * m0 - m1
    c3 = m0 + m1 - 2.0 * d
    g = la - level
    ac3 = 2.0 * abs(c3)
    up = d > 0.0
    a = 0.0
    b = 1.0
    for _ in range(100):
        f = g + s * (m0 + s * (c2 + s * c3))
        if f == 0.0:
            return s
        if (f < 0.0) == up:
            a = s
        else:
            b = s
        df = m0 + s * (2.0 * c2 + 3.0 * c3 * s)
        sn = 0.5 * (a + b)
        if df != 0.0:
            st = f / df
            if a < s - st < b:
                sn = s - st
                ast = abs(st)
                ddf = 2.0 * c2 + 6.0 * c3 * s
                if ast < 1e-10 or (abs(ddf) + ac3 * ast) * ast * ast < 2.0 * SOLVE_TOL * abs(df):
                    return sn
        if b - a < 1e-15:
            return sn
        s = sn
    return s


@njit(cache=True, error_model="numpy")
def _fractions(n, cubic, lev, pa, pb, p0, p1, sv):
    """``sv[q]``: the fraction of the interval where crossing q (0 <= q < n) occurs, or -1
    where the cubic needs the safeguarded solver.

    Linear: the clipped linear solution. Cubic: ``NEWTON_LOCKSTEP`` plain Newton steps from
    the linear solution, then one step with the error bound of ``solve_crossing``; -1 when it
    fails the bound or leaves (0, 1). Levels outside [la, lb] clip to 0 or 1 as in
    ``solve_crossing``. Branch-free over separate 1-D rows, writing only ``sv``, with an
    unsigned index (numba then emits no wraparound test per load), so that it vectorises
    (vdivpd) with the same operations per value as the scalar code: no crossing waits on
    another's divisions. (Loops over rows of the 2-D ``piece`` array updating a row in place
    do not vectorise.)
    """
    if not cubic:
        for q in range(np.uint64(n)):
            la = pa[q]
            lb = pb[q]
            s0 = (lev[q] - la) / (lb - la)
            r = 1.0 if s0 >= 1.0 else s0
            sv[q] = 0.0 if (lb == la) | (s0 <= 0.0) else r
        return
    for q in range(np.uint64(n)):
        la = pa[q]
        lb = pb[q]
        s0 = (lev[q] - la) / (lb - la)
        d = lb - la
        m0 = p0[q]
        m1 = p1[q]
        c2 = 3.0 * d - 2.0 * m0 - m1
        c3 = m0 + m1 - 2.0 * d
        g = la - lev[q]
        s = s0
        for _ in range(NEWTON_LOCKSTEP):
            f = g + s * (m0 + s * (c2 + s * c3))
            df = m0 + s * (2.0 * c2 + 3.0 * c3 * s)
            s = s - f / df
        # the checked step
        f = g + s * (m0 + s * (c2 + s * c3))
        df = m0 + s * (2.0 * c2 + 3.0 * c3 * s)
        st = f / df
        sn = s - st
        ast = abs(st)
        ddf = 2.0 * c2 + 6.0 * c3 * s
        bound = (abs(ddf) + 2.0 * abs(c3) * ast) * ast * ast
        ok = (sn > 0.0) & (sn < 1.0) & (bound < 2.0 * SOLVE_TOL * abs(df))
        r = sn if ok else -1.0
        r = 1.0 if s0 >= 1.0 else r
        sv[q] = 0.0 if (lb == la) | (s0 <= 0.0) else r


@njit(cache=True, error_model="numpy")
def _times(u0, u1, cubic, t0, dt, refractory_us, ui, utf, up_, piece, rows):
    """Times of the crossings ``u0 .. u1 - 1`` (their pieces in ``piece`` columns
    ``0 .. u1 - u0 - 1``, rows: level, la, lb, m0, m1, the pixel's ``last_t`` when listed; row
    5 is scratch), then the refractory period; returns the new end of the event list.

    The fractions come from ``_fractions`` (all crossings together); the few the cubic's
    checked step rejects are solved again by ``solve_crossing``. Events of one pixel are
    consecutive and in time order, so the refractory test runs in list order, against the
    pixel's ``last_t`` copied into the list by the rule (its row is in the cache there, not
    here) or the previous accepted event of the same pixel. (numpy error model: a division by
    zero gives inf or NaN, which the checked step rejects, instead of raising.)
    """
    lev = piece[0]
    pa = piece[1]
    pb = piece[2]
    p0 = piece[3]
    p1 = piece[4]
    sv = piece[5]
    plast = piece[6]
    _fractions(u1 - u0, cubic, lev, pa, pb, p0, p1, sv)
    w = np.uint64(u0)                      # unsigned indices: no wraparound tests
    prev = -1
    last = 0.0
    for k in range(np.uint64(u1 - u0)):
        q = np.uint64(u0) + k
        s = sv[k]
        if s < 0.0:
            s = solve_crossing(lev[k], pa[k], pb[k], p0[k], p1[k], True)
        tf = t0 + s * dt
        i = ui[q]
        if i != prev:
            prev = i
            last = plast[k]
        if tf - last < refractory_us:
            continue
        last = tf
        rows[np.uint64(i), S_LAST] = tf
        ui[w] = i
        utf[w] = tf
        up_[w] = up_[q]
        w += np.uint64(1)
    return np.int64(w)
