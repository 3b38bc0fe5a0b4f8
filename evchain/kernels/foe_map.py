"""Numba kernels of ``foe_map``: half-plane voting for the focus of expansion (Clady et al. 2014).

The map covers region A: per map row ``r`` (image row ``y0 + r``) the cells ``lo[r]..hi[r]``
(absolute image columns; ``hi < lo`` means the row is outside A). It is stored as per-row
difference arrays ``diff[r, c - x0]`` (+w at the first column of an interval, -w one past its last)
plus ``whole``, the weight of votes whose half-plane covers all of A. Weights grow as
``exp((t - t_ref) / tau)`` (lazy decay); the map is rescaled and ``t_ref`` reset before overflow.

State arrays (allocated by the filter):

* ``ist`` int64: ``[0]`` t_ref (µs), ``[1]`` next read time (µs), ``[2]`` 1 once an estimate
  exists, ``[3]`` 1 when votes arrived since the last read;
* ``fst`` float64: ``[0]`` whole, ``[1]`` last x, ``[2]`` last y, ``[3]`` last max (map units),
  ``[4]`` total weight of accepted votes (map units).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

RENORM_EXPONENT = 40.0


@njit(cache=True)
def _cond(px, py, vx, vy, q, y):
    return (px - q) * vx + (py - y) * vy > 0.0


@njit(cache=True)
def vote(diff, lo, hi, x0, y0, fst, px, py, vx, vy, w, ccx, ccy, crad):
    """Add weight ``w`` to the half-plane {q : (p - q).v > 0} inside region A.

    ``(ccx, ccy, crad)`` is a disc containing every cell of A (for the all-or-nothing shortcut).
    """
    speed = math.sqrt(vx * vx + vy * vy)
    pv = px * vx + py * vy
    cv = ccx * vx + ccy * vy
    margin = (crad + 2.0) * speed
    if cv + margin < pv:          # every cell of A in the half-plane
        fst[0] += w
        return
    if cv - margin > pv:          # no cell of A in the half-plane
        return
    ny = lo.shape[0]
    for r in range(ny):
        a = lo[r]
        b = hi[r]
        if b < a:
            continue
        yy = float(y0 + r)
        if vx == 0.0:
            if (py - yy) * vy > 0.0:
                diff[r, a - x0] += w
                diff[r, b + 1 - x0] -= w
            continue
        bound = px + (py - yy) * vy / vx
        if vx > 0.0:
            # cells q < bound: the largest such integer, fixed up with the exact test
            if bound > b + 1.0:
                k = b
            elif bound < a - 1.0:
                k = a - 1
            else:
                k = int(math.ceil(bound)) - 1
            while k + 1 <= b and _cond(px, py, vx, vy, float(k + 1), yy):
                k += 1
            while k >= a and not _cond(px, py, vx, vy, float(k), yy):
                k -= 1
            if k >= a:
                diff[r, a - x0] += w
                diff[r, k + 1 - x0] -= w
        else:
            # cells q > bound: the smallest such integer
            if bound < a - 1.0:
                k = a
            elif bound > b + 1.0:
                k = b + 1
            else:
                k = int(math.floor(bound)) + 1
            while k - 1 >= a and _cond(px, py, vx, vy, float(k - 1), yy):
                k -= 1
            while k <= b and not _cond(px, py, vx, vy, float(k), yy):
                k += 1
            if k <= b:
                diff[r, k - x0] += w
                diff[r, b + 1 - x0] -= w


@njit(cache=True)
def read_estimate(diff, lo, hi, x0, y0, whole, refine_fraction):
    """(x, y, max, min) of the map: centroid of the maximal set, refined.

    With ``refine_fraction`` f > 0 the estimate is the centroid of the cells within
    f * (max - min) of the max, weighted by their height above that threshold; with f = 0 the
    plain centroid of the maximal set (ties within a relative 1e-12).
    """
    ny = lo.shape[0]
    best = -np.inf
    worst = np.inf
    for r in range(ny):
        acc = 0.0
        for c in range(lo[r], hi[r] + 1):
            acc += diff[r, c - x0]
            v = whole + acc
            if v > best:
                best = v
            if v < worst:
                worst = v
    if not best > -np.inf:
        return np.nan, np.nan, 0.0, 0.0
    if refine_fraction > 0.0:
        thr = best - refine_fraction * (best - worst)
    else:
        thr = best - 1e-12 * abs(best)
    sx = 0.0
    sy = 0.0
    sw = 0.0
    for r in range(ny):
        acc = 0.0
        for c in range(lo[r], hi[r] + 1):
            acc += diff[r, c - x0]
            v = whole + acc
            if v >= thr:
                wt = v - thr if (refine_fraction > 0.0 and best > thr) else 1.0
                sx += wt * c
                sy += wt * (y0 + r)
                sw += wt
    if sw <= 0.0:
        return np.nan, np.nan, best, worst
    return sx / sw, sy / sw, best, worst


@njit(cache=True)
def materialize(diff, lo, hi, x0, y0, whole, out):
    """The dense map (NaN outside A) into ``out[ny, nx]`` (map units, not decayed)."""
    out[:, :] = np.nan
    for r in range(lo.shape[0]):
        acc = 0.0
        for c in range(lo[r], hi[r] + 1):
            acc += diff[r, c - x0]
            out[r, c - x0] = whole + acc


@njit(cache=True)
def process(x, y, t, vx, vy, diff, lo, hi, x0, y0, fst, ist, tau_us, min_speed_pxs,
            cos_gate, gate_on, period_us, refine_fraction, min_support, t_end,
            ccx, ccy, crad, out_t, out_x, out_y, out_sup, out_tot):
    """Vote with every flow event of a packet; read estimates at multiples of ``period_us``.

    A read at time T sees exactly the events with t < T. Reads happen before the first event at
    or after T, and at the end for every T < ``t_end``. Returns the number of estimates written.
    """
    n_out = 0
    n = t.shape[0]
    min_speed2 = min_speed_pxs * min_speed_pxs
    i = 0
    while True:
        t_next = t[i] if i < n else t_end
        # reads due before this event (or before the end of the slice)
        while ist[1] < t_next or (i < n and ist[1] == t_next):
            T = ist[1]
            if ist[3] == 1:
                ex, ey, best, worst = read_estimate(diff, lo, hi, x0, y0, fst[0],
                                                    refine_fraction)
                ist[3] = 0
                if best > 0.0 and ex == ex:
                    fst[1] = ex
                    fst[2] = ey
                    fst[3] = best
                    ist[2] = 1
            if ist[2] == 1:
                scale = math.exp(-(T - ist[0]) / tau_us)
                sup = fst[3] * scale
                if sup >= min_support and n_out < out_t.shape[0]:
                    out_t[n_out] = T
                    out_x[n_out] = fst[1]
                    out_y[n_out] = fst[2]
                    out_sup[n_out] = sup
                    out_tot[n_out] = fst[4] * scale
                    n_out += 1
            ist[1] = T + period_us
        if i >= n:
            break
        fvx = np.float64(vx[i])
        fvy = np.float64(vy[i])
        s2 = fvx * fvx + fvy * fvy
        if s2 > 0.0 and s2 >= min_speed2:
            px = float(x[i])
            py = float(y[i])
            ok = True
            if gate_on and ist[2] == 1:
                rx = px - fst[1]
                ry = py - fst[2]
                rn = math.sqrt(rx * rx + ry * ry)
                if rn > 1.0:
                    c = (rx * fvx + ry * fvy) / (rn * math.sqrt(s2))
                    ok = c >= cos_gate
            if ok:
                ti = t[i]
                e = (ti - ist[0]) / tau_us
                if e > RENORM_EXPONENT:
                    s = math.exp(-e)
                    for r in range(diff.shape[0]):
                        for c2 in range(diff.shape[1]):
                            diff[r, c2] *= s
                    fst[0] *= s
                    fst[3] *= s
                    fst[4] *= s
                    ist[0] = ti
                    e = 0.0
                w = math.exp(e)
                vote(diff, lo, hi, x0, y0, fst, px, py, fvx, fvy, w, ccx, ccy, crad)
                fst[4] += w
                ist[3] = 1
        i += 1
    return n_out
