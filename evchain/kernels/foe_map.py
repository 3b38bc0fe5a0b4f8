"""Numba kernels of ``foe_map``: half-plane voting for the focus of expansion (Clady et al. 2014).

The map covers region A, given per map row ``r`` (image row ``y0 + r``) as the columns
``lo[r]..hi[r]`` and per map column ``c`` (image column ``x0 + c``) as the rows ``clo[c]..chi[c]``
(absolute image coordinates; ``hi < lo`` means empty). A vote's boundary line crosses few rows or
few columns: a flatter line is written into per-row difference arrays ``diffR[r, x - x0]``, a
steeper one into per-column difference arrays ``diffC[y - y0, c]`` (stored row-major, so a read
is one contiguous pass). Only the rows (columns) the line crosses inside A (widened by 0.5 px) get
a write, one each: an interval either starts at the row's first cell (then the whole row gets +w
through ``constR``, a difference array over rows, and -w goes where the interval ends) or ends
at its last cell (then only its start is written: prefix sums stop at the last cell). The rows
(columns) before and after that range lie wholly on one side of the line, so they get one range
update each in ``constR`` (``constC``). Votes whose half-plane holds all of A, or none, cost
O(1). So the cost per event is O(rows the line crosses), at most O(rows), and the map equals the
brute-force sum cell by cell.

Weights grow as ``exp((t - t_ref) / tau)`` (lazy decay); the map is rescaled and ``t_ref`` reset
before overflow.

State (:class:`FoeMapState`, from :func:`new_state`; constants: :func:`new_params`):

* the maps: ``diffR`` [rows, cols + 1], ``diffC`` [rows + 1, cols], ``constC`` [cols + 1] and
  ``rowv`` [3, rows + 1]: ``constR`` (row :data:`CONST_R`) and two difference arrays over rows
  for the reads' bounds: the weight of the votes that covered a whole row (the caps, row
  :data:`CAPS`) and of the votes that may have reached part of it (the rows a boundary crosses;
  a column-wise vote: all; row :data:`TOUCH`); the bounds are reset at a renormalisation;
* region A: ``lo``, ``hi`` per map row, ``clo``, ``chi`` per map column;
* ``rows`` float64 [rows, 6]: per map row (columns :data:`ROW_MAX` .. :data:`ROW_FULL`) its max
  and min when last computed, the ``whole`` votes then, the touching weight then, 1 if valid,
  and the whole-row weight then (reads recompute only the rows that can matter, see
  :func:`refresh`; a renormalisation invalidates all);
* ``carry``: one record of :data:`CARRY`: the weights' reference time ``t_ref`` (µs), the next
  read (µs), whether an estimate exists and whether votes arrived since the last read; the
  votes covering all of A (``whole``), the last estimate (x, y, its maximum), the total
  weight of accepted votes (map units), the sum of their squared weights (``total2``) and the
  number of estimates dropped at noise level (``noise_level``);
* ``mbuf`` [rows, cols]: the dense map of a read.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from evchain.kernels.intrinsics import float_bits, from_bits

#: rows of ``rowv``: constR, the caps' and the touching votes' difference arrays
CONST_R, CAPS, TOUCH = range(3)
#: columns of ``rows``: the row's max and min when last computed, the whole votes, touching
#: and whole-row weights then, and 1 if valid
ROW_MAX, ROW_MIN, ROW_WHOLE, ROW_TOUCH, ROW_VALID, ROW_FULL = range(6)
CARRY = np.dtype([("t_ref", "i8"), ("next_read", "i8"), ("has_estimate", "i8"), ("dirty", "i8"),
                  ("whole", "f8"), ("est_x", "f8"), ("est_y", "f8"), ("est_max", "f8"),
                  ("total", "f8"), ("total2", "f8"), ("noise_level", "i8")])


#: the constants of :func:`process` (one record, not a named tuple: numba types it faster per
#: call, and a packet's votes are cheap); fields as in :class:`~evchain.filters.foe_map.FoeMap`'s
#: parameters, in µs, px/s and map cells; ``cos_gate``: cos of the gate's largest angle;
#: ``noise_test``: drop estimates whose consensus is at noise level (:func:`_above_noise`), with
#: ``log_m_alpha`` = ln(M / significance), M the cells of A
PARAMS = np.dtype([("tau_us", "f8"), ("min_speed_pxs", "f8"), ("gate_on", "?"),
                   ("cos_gate", "f8"), ("period_us", "i8"), ("refine_fraction", "f8"),
                   ("min_support", "f8"), ("speed_w0", "f8"), ("cx", "f8"), ("cy", "f8"),
                   ("radius", "f8"), ("x0", "i8"), ("y0", "i8"), ("noise_test", "?"),
                   ("log_m_alpha", "f8")])


def new_params(**values) -> np.ndarray:
    """The constants of :func:`process` as one :data:`PARAMS` record; every field is needed."""
    if set(values) != set(PARAMS.names):
        raise TypeError(f"foe_map params: expected {PARAMS.names}, got {sorted(values)}")
    return np.array([tuple(values[name] for name in PARAMS.names)], PARAMS)


class FoeMapState(NamedTuple):
    """The state of :func:`process` (see the module docstring), from :func:`new_state`."""

    diffR: np.ndarray
    diffC: np.ndarray
    constC: np.ndarray
    rowv: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    clo: np.ndarray
    chi: np.ndarray
    rows: np.ndarray
    carry: np.ndarray
    mbuf: np.ndarray


def new_state(lo: np.ndarray, hi: np.ndarray, clo: np.ndarray, chi: np.ndarray) -> FoeMapState:
    """Empty maps over region A, given by its rows' column bounds ``lo``, ``hi`` and its
    columns' row bounds ``clo``, ``chi`` (int64, absolute cells; hi < lo: empty)."""
    ny, nx = len(lo), len(clo)
    rows = np.zeros((ny, 6), np.float64)
    rows[:, ROW_MAX] = -np.inf
    return FoeMapState(np.zeros((ny, nx + 1)), np.zeros((ny + 1, nx)), np.zeros(nx + 1),
                       np.zeros((3, ny + 1)), np.asarray(lo, np.int64), np.asarray(hi, np.int64),
                       np.asarray(clo, np.int64), np.asarray(chi, np.int64), rows,
                       np.zeros(1, CARRY), np.empty((ny, nx)))


def start(state: FoeMapState, first_read_us: int) -> None:
    """Set the first read (µs)."""
    state.carry["next_read"] = first_read_us


def forget_row_bounds(state: FoeMapState) -> None:
    """Make the next read recompute every row (as after a renormalisation)."""
    state.rows[:, ROW_VALID] = 0.0


def dense_map(state: FoeMapState, x0: int, t_us: int, tau_us: float) -> np.ndarray:
    """The dense vote map decayed to ``t_us`` (NaN outside region A)."""
    out = np.empty_like(state.mbuf)
    materialize(state.diffR, state.rowv[CONST_R], state.diffC, state.constC, state.lo, state.hi,
                x0, float(state.carry["whole"][0]), out, np.empty(len(out)))
    return out * math.exp(-(t_us - int(state.carry["t_ref"][0])) / tau_us)

RENORM_EXPONENT = 40.0
#: the disc around A that decides which votes cover all of A, none or part, and which rows
#: (columns) a boundary crosses: A's radius plus this (A's cells lie inside A's radius)
MARGIN_PX = 0.5
#: a row bound (|bound| < 1e6 px) this close to a cell centre, 0.5 - NEAR, is checked with the
#: exact test of the brute force (its rounding error is < 1e-9 px)
NEAR = 0.5 - 1e-9


@njit(cache=True, error_model="numpy", inline="always")
def _cond(px, py, vx, vy, qx, qy):
    """The exact test of the brute force: is cell q in the half-plane {q : (p - q).v > 0}?"""
    return (px - qx) * vx + (py - qy) * vy > 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _first(a, b, yy, px, py, vx, vy, slope):
    """Row yy, cells a..b, vx != 0: the first cell where the half-plane indicator changes, in
    [a, b + 1]: the first cell outside for vx > 0 (the half-plane is qx < bound), the first
    inside for vx < 0 (qx > bound). Computed directly; fixed up with the exact test of the
    brute force only when the boundary lies within 1e-9 px of a cell centre (a bound beyond
    a - 0.5 or b + 0.5 gives a or b + 1 whatever its rounding). A column is the same call with
    x and y swapped (``_cond`` is symmetric in them, exactly: its sum commutes)."""
    bound = min(max(px + (py - yy) * slope, a - 0.5), b + 0.5)
    kf = math.floor(bound)
    k = int(kf) + 1
    if abs(bound - kf - 0.5) > NEAR:
        if vx > 0.0:
            while k <= b and _cond(px, py, vx, vy, float(k), yy):
                k += 1
            while k > a and not _cond(px, py, vx, vy, float(k - 1), yy):
                k -= 1
        else:
            while k - 1 >= a and _cond(px, py, vx, vy, float(k - 1), yy):
                k -= 1
            while k <= b and not _cond(px, py, vx, vy, float(k), yy):
                k += 1
    return k


@njit(cache=True, error_model="numpy")
def materialize(diffR, constR, diffC, constC, lo, hi, x0, whole, out, rowmax):
    """The dense map (NaN outside A) into ``out[ny, nx]`` (map units, not decayed) and each
    row's maximum into ``rowmax[ny]`` (-inf for a row outside A); returns the (max, min) over A
    (-inf, inf when A is empty). One pass, row by row: the per-column prefix sums advance one
    row at a time (entries outside a column's rows of A never matter)."""
    ny, nx = out.shape
    ccum = np.cumsum(constC)      # sequential, the same sums as a loop
    cacc = np.zeros(nx, np.float64)
    best = -np.inf
    worst = np.inf
    rc = 0.0
    for r in range(ny):
        rc += constR[r]
        for c in range(nx):
            cacc[c] += diffC[r, c]
        acc = 0.0
        base = whole + rc
        a = lo[r] - x0
        b = hi[r] - x0
        for c in range(0, min(a, nx)):
            out[r, c] = np.nan
        for c in range(max(b + 1, 0), nx):
            out[r, c] = np.nan
        rbest = -np.inf
        for c in range(a, b + 1):
            acc += diffR[r, c]
            v = base + acc + ccum[c] + cacc[c]
            out[r, c] = v
            if v > rbest:
                rbest = v
            if v < worst:
                worst = v
        rowmax[r] = rbest
        if rbest > best:
            best = rbest
    return best, worst


@njit(cache=True, error_model="numpy")
def _row_prefixes(diffR, lo, hi, x0, need, out):
    """``out[r, c]`` = prefix sum of ``diffR[r, a..c]`` over each needed row's cells a..b, four
    rows at a time (independent add chains: a single row's chain is latency-bound). Entries of
    ``diffR`` left of a row's first cell are zero, so starting further left changes nothing;
    cells right of b get values that are never used."""
    rows = np.nonzero(need)[0]
    m = rows.shape[0]
    for g in range(0, m, 4):
        r0 = rows[g]
        r1 = rows[min(g + 1, m - 1)]
        r2 = rows[min(g + 2, m - 1)]
        r3 = rows[min(g + 3, m - 1)]
        c0 = np.uint64(min(min(lo[r0], lo[r1]), min(lo[r2], lo[r3])) - x0)
        c1 = np.uint64(max(max(hi[r0], hi[r1]), max(hi[r2], hi[r3])) - x0 + 1)
        a0 = a1 = a2 = a3 = 0.0
        for c in range(c0, c1):
            a0 += diffR[r0, c]
            a1 += diffR[r1, c]
            a2 += diffR[r2, c]
            a3 += diffR[r3, c]
            out[r0, c] = a0
            out[r1, c] = a1
            out[r2, c] = a2
            out[r3, c] = a3


_SIGN = np.int64(0x7FFFFFFFFFFFFFFF)


@njit(cache=True, error_model="numpy")
def refresh(diffR, rowv, diffC, constC, lo, hi, x0, whole, total, rst, out, refine_fraction):
    """Bring up to date the rows of the dense map ``out`` (map units) that this read needs;
    returns the (max, min) over A (-inf, inf when A is empty) and sets ``rst[:, ROW_MAX]`` to
    each needed row's maximum (rows left out stay below the read's threshold). ``whole``: the
    votes covering all of A, ``total``: all accepted votes.

    ``rst[r]`` holds row r's maximum and minimum when it was last computed, the ``whole`` votes
    and the row's whole-row and touching weights (prefix sums of ``rowv[CAPS]``, of
    ``rowv[CAPS]`` plus ``rowv[TOUCH]``) at that time, and 1 if valid (0 forces a
    recomputation). Votes only add, so since then every cell of the row rose by at least the
    ``whole`` plus the whole-row difference and at most the ``whole`` plus the touching
    difference: bounds on the row's maximum and minimum now. Only rows that can hold the
    maximum, the minimum or a cell above the lowest possible threshold are recomputed (the same
    prefix sums in the same order as :func:`materialize`, so the same values bit for bit); the
    pass over ``diffC`` stops at the last of them.
    """
    ny, nx = out.shape
    constR = rowv[CONST_R]
    eps = 1e-12 * total
    full = np.empty(ny)    # per row: the partial votes' weight that covered all of it
    touch = np.empty(ny)   # and that reached any of its cells
    fa = 0.0
    ta = 0.0
    for r in range(ny):
        fa += rowv[CAPS, r]
        ta += rowv[TOUCH, r]
        full[r] = fa
        touch[r] = fa + ta
    lbest = -np.inf    # the maximum is at least this
    uworst = np.inf    # the minimum is at most this
    lworst = np.inf    # and at least this
    every = False      # a row without valid bounds: recompute all
    for r in range(ny):
        if hi[r] < lo[r]:
            continue
        if rst[r, ROW_VALID] == 0.0:
            every = True
            break
        up = whole - rst[r, ROW_WHOLE]
        lup = up + (full[r] - rst[r, ROW_FULL])
        hup = up + (touch[r] - rst[r, ROW_TOUCH])
        lbest = max(lbest, rst[r, ROW_MAX] + lup - eps)
        uworst = min(uworst, rst[r, ROW_MIN] + hup + eps)
        lworst = min(lworst, rst[r, ROW_MIN] + lup - eps)
    if refine_fraction > 0.0:
        lthr = lbest - refine_fraction * (lbest - lworst)
    else:
        lthr = lbest - 1e-12 * abs(lbest)
    lthr = min(lthr, lbest) - eps
    last = -1
    need = np.zeros(ny, np.bool_)
    for r in range(ny):
        if hi[r] < lo[r]:
            continue
        up = whole - rst[r, ROW_WHOLE]
        if (every or rst[r, ROW_MAX] + up + (touch[r] - rst[r, ROW_TOUCH]) + eps >= lthr
                or rst[r, ROW_MIN] + up + (full[r] - rst[r, ROW_FULL]) - eps <= uworst):
            need[r] = True
            last = r
    _row_prefixes(diffR, lo, hi, x0, need, out)
    cacc = np.zeros(nx, np.float64)
    ccum = np.cumsum(constC)
    best = -np.inf
    worst = np.inf
    rc = 0.0
    for r in range(last + 1):
        rc += constR[r]
        for c in range(nx):
            cacc[c] += diffC[r, c]
        if need[r]:
            # the map values (the same sums in the same order as materialize) and, in the same
            # pass, the row's extrema over their order-preserving int64 keys: integer max/min
            # reductions vectorise, floating-point ones do not
            # (unsigned indices: numba's negative-index wraparound stops vectorisation)
            a = np.uint64(lo[r] - x0)
            b = np.uint64(hi[r] - x0 + 1)
            base = whole + rc
            kb = np.int64(-0x7FFFFFFFFFFFFFFF)
            kw = np.int64(0x7FFFFFFFFFFFFFFF)
            for c in range(a, b):
                v = base + out[r, c] + ccum[c] + cacc[c]
                out[r, c] = v
                k = float_bits(v)
                k = k ^ ((k >> 63) & _SIGN)
                kb = max(kb, k)
                kw = min(kw, k)
            rbest = from_bits(kb ^ ((kb >> 63) & _SIGN))
            rworst = from_bits(kw ^ ((kw >> 63) & _SIGN))
            rst[r, ROW_MAX] = rbest
            rst[r, ROW_MIN] = rworst
            rst[r, ROW_WHOLE] = whole
            rst[r, ROW_TOUCH] = touch[r]
            rst[r, ROW_VALID] = 1.0
            rst[r, ROW_FULL] = full[r]
            best = max(best, rbest)
            worst = min(worst, rworst)
    return best, worst


@njit(cache=True, error_model="numpy")
def _cell_weight(v, thr, weighted):
    if weighted:
        return max(v - thr, 0.0)
    return 1.0 if v >= thr else 0.0


@njit(cache=True, error_model="numpy")
def _row_sums(m, r, a, b, thr, weighted):
    """Row r of ``m``, cells a..b - 1: the sums of the weights w and of w * column index, where
    w = (v - thr) for cells v >= thr (``weighted``) or 1 for them. Four interleaved partial
    sums in a fixed order (four independent chains of additions), so the result does not
    depend on how the code was compiled: a reassociated (``fastmath``) loop gave other last
    bits fresh from the JIT than loaded from numba's cache."""
    sw0 = sw1 = sw2 = sw3 = 0.0
    sc0 = sc1 = sc2 = sc3 = 0.0
    one, four = np.uint64(1), np.uint64(4)
    c = a
    while c + four <= b:
        w0 = _cell_weight(m[r, c], thr, weighted)
        w1 = _cell_weight(m[r, c + one], thr, weighted)
        w2 = _cell_weight(m[r, c + one + one], thr, weighted)
        w3 = _cell_weight(m[r, c + four - one], thr, weighted)
        sw0 += w0
        sw1 += w1
        sw2 += w2
        sw3 += w3
        sc0 += w0 * np.float64(c)
        sc1 += w1 * (np.float64(c) + 1.0)
        sc2 += w2 * (np.float64(c) + 2.0)
        sc3 += w3 * (np.float64(c) + 3.0)
        c += four
    while c < b:
        w0 = _cell_weight(m[r, c], thr, weighted)
        sw0 += w0
        sc0 += w0 * np.float64(c)
        c += one
    return (sw0 + sw1) + (sw2 + sw3), (sc0 + sc1) + (sc2 + sc3)


@njit(cache=True, error_model="numpy")
def read_estimate(m, x0, y0, best, worst, refine_fraction, lo, hi, rowmax):
    """(x, y) of a dense map ``m`` (NaN outside A; row r holds A's columns ``lo[r]..hi[r]``,
    its maximum is ``rowmax[r]``) with maximum ``best`` and minimum ``worst``: centroid of the
    maximal set, refined. Rows whose maximum is below the threshold are skipped; the others are
    summed row by row (:func:`_row_sums`).

    With ``refine_fraction`` f > 0 the estimate is the centroid of the cells within
    f * (max - min) of the max, weighted by their height above that threshold; with f = 0 the
    plain centroid of the maximal set (ties within a relative 1e-12).
    """
    ny, nx = m.shape
    if not best > -np.inf:
        return np.nan, np.nan
    if refine_fraction > 0.0:
        thr = best - refine_fraction * (best - worst)
    else:
        thr = best - 1e-12 * abs(best)
    weighted = refine_fraction > 0.0 and best > thr
    sx = 0.0
    sy = 0.0
    sw = 0.0
    for r in range(ny):
        if not rowmax[r] >= thr:
            continue
        a = np.uint64(lo[r] - x0)
        b = np.uint64(hi[r] - x0 + 1)
        rw, rc = _row_sums(m, r, a, b, thr, weighted)
        sw += rw
        sx += rc
        sy += rw * np.float64(y0 + r)
    if sw <= 0.0:
        return np.nan, np.nan
    return x0 + sx / sw, sy / sw


@njit(cache=True, error_model="numpy", inline="always")
def _span(m, h, origin, count, disc):
    """The lines (index from ``origin``, within 0 .. count - 1) the chord with centre ``m``,
    half-extent ``h`` crosses; (count, count - 1) when it misses the disc."""
    k0 = max(int(math.floor(m - h)) - origin, 0)
    k1 = min(int(math.ceil(m + h)) - origin, count - 1)
    if disc <= 0.0 or k0 > k1:
        return count, count - 1
    return k0, k1


@njit(cache=True, error_model="numpy")
def _renormalise(state, s):
    """Scale every map by ``s`` (the weights' reference time moves on); forget the rows' bounds."""
    diffR, diffC, constC, rowv = state.diffR, state.diffC, state.constC, state.rowv
    # element loops: array expressions here put refcount operations into every iteration of
    # the event loop (measured: 6x slower overall)
    for a in range(diffR.shape[0]):
        for b in range(diffR.shape[1]):
            diffR[a, b] *= s
    for a in range(rowv.shape[1]):
        rowv[CONST_R, a] *= s
    for a in range(diffC.shape[0]):
        for b in range(diffC.shape[1]):
            diffC[a, b] *= s
    for a in range(constC.shape[0]):
        constC[a] *= s
    state.carry[0].est_max *= s
    for a in range(state.rows.shape[0]):
        state.rows[a, ROW_VALID] = 0.0
    for a in range(rowv.shape[1]):
        rowv[CAPS, a] = 0.0
        rowv[TOUCH, a] = 0.0


@njit(cache=True, error_model="numpy")
def _read(state, prm, T, whole, total, dirty):
    """The read at T: recompute the estimate when votes arrived since the last one (``dirty``);
    returns whether there is an estimate."""
    g = state.carry[0]
    if dirty == 1:
        g.whole = whole
        g.total = total
        best, worst = refresh(state.diffR, state.rowv, state.diffC, state.constC, state.lo,
                              state.hi, prm.x0, whole, total, state.rows, state.mbuf,
                              prm.refine_fraction)
        ex, ey = read_estimate(state.mbuf, prm.x0, prm.y0, best, worst, prm.refine_fraction,
                               state.lo, state.hi, state.rows[:, ROW_MAX])
        if best > 0.0 and ex == ex:
            g.est_x = ex
            g.est_y = ey
            g.est_max = best
            g.has_estimate = 1
    return g.has_estimate == 1


@njit(cache=True, error_model="numpy", inline="always")
def _accepted(px, py, fvx, fvy, s2, g, prm):
    """A flow event votes: fast enough and, with the angular gate and an estimate, pointing
    away from the estimate within the gate (events within 1 px of it pass)."""
    if not (s2 > 0.0 and s2 >= prm.min_speed_pxs * prm.min_speed_pxs):
        return False
    if not (prm.gate_on and g.has_estimate == 1):
        return True
    rx = px - g.est_x
    ry = py - g.est_y
    rn = math.sqrt(rx * rx + ry * ry)
    return not rn > 1.0 or (rx * fvx + ry * fvy) / (rn * math.sqrt(s2)) >= prm.cos_gate


@njit(cache=True, error_model="numpy", inline="always")
def _above_noise(sup, tot, total, total2, prm):
    """Whether an estimate's consensus ``sup / tot`` exceeds the noise bound
    1/2 + sqrt(ln(M / significance) / (2 n)), n = total^2 / total2 the effective number of
    votes (always true without ``prm.noise_test``)."""
    if not prm.noise_test:
        return True
    n = total * total / total2 if total2 > 0.0 else 0.0
    return n > 0.0 and sup > (0.5 + math.sqrt(prm.log_m_alpha / (2.0 * n))) * tot


@njit(cache=True, error_model="numpy", nogil=True)
def process(x, y, t, vx, vy, state, prm, t_end, out):
    """Vote with every flow event of a packet; read estimates at multiples of ``period_us``.

    A read at time T sees exactly the events with t < T. Reads happen before the first event at
    or after T, and at the end for every T < ``t_end``. Each vote covers all of A (O(1)), none
    of it, or the rows (columns) its boundary crosses plus two caps.

    Parameters
    ----------
    x, y : ndarray, shape (n,)
        Flow events' positions in map cells (uint16 pixels, or float64 cells).
    t : int64 ndarray, shape (n,)
        Their times, µs, non-decreasing.
    vx, vy : float32 ndarray, shape (n,)
        Their flow, px/s (cells/s).
    state : tuple
        The arrays of a :class:`FoeMapState` (:func:`new_state`, :func:`start`), updated in
        place; best as a plain tuple (``tuple(state)``): numba types it faster per call.
    prm : PARAMS ndarray, shape (1,)
        The constants (:func:`new_params`).
    t_end : int
        End of the packet's time slice, µs.
    out : structured ndarray (t, x, y, support, total)
        Out: the estimates (t µs, position in cells, decayed support and total votes); an
        estimate at noise level (:func:`_above_noise`) is not written but counted in
        ``carry.noise_level``.

    Returns
    -------
    int
        The number of estimates written into ``out``.
    """
    diffR, diffC, constC, rowv, lo, hi, clo, chi, rows, carry, mbuf = state
    st = FoeMapState(diffR, diffC, constC, rowv, lo, hi, clo, chi, rows, carry, mbuf)
    g = carry[0]
    p = prm[0]
    tau_us = p.tau_us
    cx, cy, x0, y0 = p.cx, p.cy, p.x0, p.y0
    rr = p.radius + MARGIN_PX
    rr2 = rr * rr
    n_out = 0
    n = t.shape[0]
    # the state updated per event lives in locals (stores into the maps could alias the state
    # arrays, so LLVM would reload and store these every event); written back at the end and
    # before a read
    t_ref = g.t_ref
    t_read = g.next_read
    dirty = g.dirty
    whole = g.whole
    total = g.total
    total2 = g.total2
    t_w = t_ref - 1  # w_t = the weight of a vote at time t_w
    w_t = math.exp((t_w - t_ref) / tau_us)
    i = 0
    while True:
        t_next = t[i] if i < n else t_end
        # reads due before this event (or before the end of the slice)
        while t_read < t_next or (i < n and t_read == t_next):
            if _read(st, p, t_read, whole, total, dirty):
                scale = math.exp(-(t_read - t_ref) / tau_us)
                sup = g.est_max * scale
                if sup >= p.min_support and n_out < out.shape[0]:
                    tot = total * scale
                    if _above_noise(sup, tot, total, total2, p):
                        _emit(out, n_out, t_read, g.est_x, g.est_y, sup, tot)
                        n_out += 1
                    else:
                        g.noise_level += 1
            dirty = 0
            t_read = t_read + p.period_us
        if i >= n:
            break
        fvx = np.float64(vx[i])
        fvy = np.float64(vy[i])
        s2 = fvx * fvx + fvy * fvy
        px = float(x[i])
        py = float(y[i])
        if _accepted(px, py, fvx, fvy, s2, g, p):
            ti = t[i]
            if ti != t_w:  # most flow events share their time with the one before: same w
                e = (ti - t_ref) / tau_us
                if e > RENORM_EXPONENT:
                    s = math.exp(-e)
                    _renormalise(st, s)
                    whole *= s
                    total *= s
                    total2 *= s * s
                    t_ref = ti
                    e = 0.0
                w_t = math.exp(e)
                t_w = ti
            w = w_t
            if p.speed_w0 > 0.0:  # tight constraints (slow normal flow) weigh more
                w *= p.speed_w0 / (p.speed_w0 + math.sqrt(s2))
            speed = math.sqrt(s2)
            # distance of the boundary from A's centre c, times the speed
            dn = (px * fvx + py * fvy) - (cx * fvx + cy * fvy)
            margin = rr * speed
            if dn > margin:               # every cell of A in the half-plane
                whole += w
            elif dn >= -margin:           # otherwise no cell of A is in the half-plane
                # the chord of the line {q : q.v = p.v} through the disc (c, rr): centre
                # c + dn v / |v|^2, half-extent sqrt(rr^2 |v|^2 - dn^2) / |v|^2 along it
                inv = 1.0 / s2
                disc = rr2 * s2 - dn * dn
                sq = math.sqrt(disc) * inv if disc > 0.0 else 0.0
                # the votes are written out here, not in functions inlined by numba: their
                # array arguments cost atomic refcount operations at every vote
                if abs(fvx) >= abs(fvy):
                    # a boundary steeper than 45 degrees: the columns it crosses (chord centre
                    # xm +- hx) get their interval's start in diffC (and the whole column in
                    # constC for an interval that starts at the column's first cell); the
                    # columns before and after, wholly on one side, one range update each in
                    # constC; every row may be reached (rowv[TOUCH])
                    xm = cx + dn * fvx * inv
                    hx = sq * abs(fvy)
                    ncol = clo.shape[0]
                    rowv[TOUCH, 0] += w
                    rowv[TOUCH, rowv.shape[1] - 1] -= w
                    k0, k1 = _span(xm, hx, x0, ncol, disc)
                    # vy > 0: +w to the columns' rows before the boundary (constC), -w from it
                    # on; vy < 0: +w from it on. One path for both (selects, not branches: the
                    # sign is random); adding 0.0 changes nothing. vy = 0: +w to the whole
                    # column where its first cell is inside
                    level = fvy == 0.0
                    sl = fvx / fvy
                    cw = w if fvy > 0.0 else 0.0
                    sw = -w if fvy > 0.0 else w
                    u0, u1 = k0, k1 + 1
                    if level:
                        for c in range(u0, u1):
                            if chi[c] >= clo[c] and (px - (x0 + c)) * fvx > 0.0:
                                diffC[clo[c] - y0, c] += w
                    else:
                        if k1 >= k0:
                            constC[k0] += cw
                            constC[k1 + 1] -= cw
                        for c in range(u0, u1):
                            if chi[c] >= clo[c]:
                                k = _first(clo[c], chi[c], float(x0 + c), py, px, fvy, fvx, sl)
                                diffC[k - y0, c] += sw
                    # the columns before and after: wholly on one side; test one cell each
                    c = min(k0, ncol) - 1
                    while c >= 0 and chi[c] < clo[c]:
                        c -= 1
                    cc = max(c, 0)
                    cw = (w if (c >= 0) & _cond(px, py, fvx, fvy, float(x0 + cc), float(clo[cc]))
                          else 0.0)
                    constC[0] += cw
                    constC[min(k0, ncol)] -= cw
                    first = k1 + 1 if k1 >= k0 else ncol
                    c = first
                    while c < ncol and chi[c] < clo[c]:
                        c += 1
                    cc = min(c, ncol - 1)
                    cw = (w if (c < ncol) & _cond(px, py, fvx, fvy, float(x0 + cc), float(clo[cc]))
                          else 0.0)
                    constC[first] += cw
                    constC[ncol] -= cw
                else:
                    # flatter than 45 degrees: the same with rows and columns swapped (diffR,
                    # rowv[CONST_R]), and the rows crossed, before and after recorded for the
                    # reads' bounds (rowv[TOUCH], rowv[CAPS])
                    ym = cy + dn * fvy * inv
                    hy = sq * abs(fvx)
                    nrow = lo.shape[0]
                    k0, k1 = _span(ym, hy, y0, nrow, disc)
                    if k1 >= k0:
                        rowv[TOUCH, k0] += w
                        rowv[TOUCH, k1 + 1] -= w
                    level = fvx == 0.0
                    sl = fvy / fvx
                    cw = w if fvx > 0.0 else 0.0
                    sw = -w if fvx > 0.0 else w
                    u0, u1 = k0, k1 + 1
                    if level:
                        for r in range(u0, u1):
                            if hi[r] >= lo[r] and (py - (y0 + r)) * fvy > 0.0:
                                diffR[r, lo[r] - x0] += w
                    else:
                        if k1 >= k0:
                            rowv[CONST_R, k0] += cw
                            rowv[CONST_R, k1 + 1] -= cw
                        for r in range(u0, u1):
                            if hi[r] >= lo[r]:
                                k = _first(lo[r], hi[r], float(y0 + r), px, py, fvx, fvy, sl)
                                diffR[r, k - x0] += sw
                    r = min(k0, nrow) - 1
                    while r >= 0 and hi[r] < lo[r]:
                        r -= 1
                    rc = max(r, 0)
                    cw = (w if (r >= 0) & _cond(px, py, fvx, fvy, float(lo[rc]), float(y0 + rc))
                          else 0.0)
                    rowv[CONST_R, 0] += cw
                    rowv[CONST_R, min(k0, nrow)] -= cw
                    rowv[CAPS, 0] += cw
                    rowv[CAPS, min(k0, nrow)] -= cw
                    first = k1 + 1 if k1 >= k0 else nrow
                    r = first
                    while r < nrow and hi[r] < lo[r]:
                        r += 1
                    rc = min(r, nrow - 1)
                    cw = (w if (r < nrow) & _cond(px, py, fvx, fvy, float(lo[rc]), float(y0 + rc))
                          else 0.0)
                    rowv[CONST_R, first] += cw
                    rowv[CONST_R, nrow] -= cw
                    rowv[CAPS, first] += cw
                    rowv[CAPS, nrow] -= cw
            total += w
            total2 += w * w
            dirty = 1
        i += 1
    g.t_ref = t_ref
    g.next_read = t_read
    g.dirty = dirty
    g.whole = whole
    g.total = total
    g.total2 = total2
    return n_out


@njit(cache=True, error_model="numpy", inline="always")
def _emit(out, n, T, x, y, support, total):  # one estimate
    out[n].t = T
    out[n].x = x
    out[n].y = y
    out[n].support = support
    out[n].total = total
