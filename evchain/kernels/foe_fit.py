"""Numba kernel of ``foe_fit``: the FOE from normal-flow magnitudes with a piecewise-planar scene.

For pure translation a point at image position p with inverse time to contact ``g`` has flow
``(p - foe) g``; its normal flow along the unit normal n has speed ``s = (p - foe).n g``. Three
planes are modelled, each with its own scale: the road seen by a level camera (``g = a0 dy``,
``dy = y - y_foe`` rows below the FOE), a facade left of the FOE (``g = a1 (x_foe - x)``) and one
right of it (``g = a2 (x - x_foe)``). Unknowns ``th = (x_foe, y_foe, a0, a1, a2)``.

A fit is iteratively reweighted Gauss-Newton: every event within ``margin`` px of a plane's
vanishing line is left out of that plane; each remaining event is assigned to the plane that
predicts its speed best and weighs ``w_t (1 - (e/c)^2)^2 / pred^2`` (Tukey on the residual
relative to the predicted speed, ``e = |s - pred| / pred``, decay ``w_t`` by age): the flow's
error grows with the true speed, of which ``pred`` is the model's estimate; dividing by the
measured ``s`` instead favours speeds measured too slow. Converging events (``(p - foe).n <=
0``) and events without a positive prediction are left out. A plane's scale without a value
starts as the weighted median of ``s / ((p - foe).n d)`` of its events; for the facades only
of events above the FOE's row, where a level camera sees no road (below it the road's events,
far more numerous, would set the facades' scales several times too large, a wrong local
minimum the fit does not leave).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

#: the unknowns ``th``: the FOE (px) and the three planes' scales (road, left, right facade)
FOE_X, FOE_Y, ROAD, LEFT, RIGHT = range(5)
NP = 5


class FitEvents(NamedTuple):
    """The flow events a fit sees (float64 arrays, one entry per event, in time order)."""

    x: np.ndarray   #: position, px
    y: np.ndarray
    nx: np.ndarray  #: unit normal (the flow's direction)
    ny: np.ndarray
    s: np.ndarray   #: normal flow speed, px/s (> 0)
    e: np.ndarray   #: decay weight exp((t - t_ref) / tau)


class FitParams(NamedTuple):
    """Constants of :func:`fit`; build with :func:`evchain.kernels.records.record`."""

    margin: float     #: events this close to a plane's vanishing line are left out of it, px
    tolerance: float  #: Tukey constant on the relative speed residual
    max_iter: int     #: Gauss-Newton iterations
    max_step: float   #: largest FOE step per iteration, px


def initial_theta(foe_x: float, foe_y: float) -> np.ndarray:
    """Unknowns for a fit starting at the FOE (foe_x, foe_y), the planes' scales unknown."""
    th = np.full(NP, np.nan)
    th[FOE_X] = foe_x
    th[FOE_Y] = foe_y
    return th


@njit(cache=True, error_model="numpy")
def solve(A, b):
    """x with A x = b by Gaussian elimination with partial pivoting (A, b are overwritten);
    returns False when a pivot is zero."""
    n = len(b)
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[p, k]):
                p = i
        if A[p, k] == 0.0:
            return False
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            b[k], b[p] = b[p], b[k]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= f * A[k, j]
            b[i] -= f * b[k]
    for k in range(n - 1, -1, -1):
        acc = b[k]
        for j in range(k + 1, n):
            acc -= A[k, j] * b[j]
        b[k] = acc / A[k, k]
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _lever(k, dxx, dyy):
    """The plane's factor d: dy for the road, -dx left, dx right."""
    if k == 0:
        return dyy
    return -dxx if k == 1 else dxx


@njit(cache=True, error_model="numpy", inline="always")
def _applies(k, dxx, dyy, margin):
    if k == 0:
        return dyy > margin
    return -dxx > margin if k == 1 else dxx > margin


@njit(cache=True, error_model="numpy")
def _weighted_median(r, w, m):
    """The weighted median of ``r[:m]`` (weights ``w[:m]``): the first value in sorted order
    where the cumulative weight reaches half the total; NaN when none does."""
    o = np.argsort(r[:m])
    half = 0.0
    for j in range(m):
        half += w[j]
    half *= 0.5
    acc = 0.0
    for j in range(m):
        acc += w[o[j]]
        if acc >= half:
            return r[o[j]]
    return np.nan


@njit(cache=True, error_model="numpy")
def _init_scales(x, y, nx, ny, s, e, g, i0, i1, th, margin):
    """Each plane scale without a value: the weighted median of s / ((p - foe).n d) over the
    plane's events (the facades' only above the FOE's row); left NaN without events."""
    for k in range(3):
        if not math.isnan(th[ROAD + k]):
            continue
        r = np.empty(i1 - i0)
        w = np.empty(i1 - i0)
        m = 0
        for i in range(i0, i1):
            dxx = x[i] - th[FOE_X]
            dyy = y[i] - th[FOE_Y]
            dn = dxx * nx[i] + dyy * ny[i]
            if dn > 0.0 and _applies(k, dxx, dyy, margin) and (k == 0 or dyy < -margin):
                r[m] = s[i] / (dn * _lever(k, dxx, dyy))
                w[m] = e[i] * g
                m += 1
        if m > 0:
            med = _weighted_median(r, w, m)
            if not math.isnan(med):
                th[ROAD + k] = med


@njit(cache=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _sums(x, y, nx, ny, s, e, i0, i1, g, th, margin, c):
    """One pass of the Gauss-Newton normal equations at ``th``: the 19 sums
    (a00, a01, a11, b0, b1, inlier weight, applicable weight, then per plane road / left /
    right: w J0 Ja, w J1 Ja, w Ja Ja, w r Ja). Branch-free (selects, one accumulator per sum,
    reassociated) so that LLVM vectorises it; the sums' order differs from a plain loop only
    in rounding."""
    xf, yf = th[0], th[1]
    has_road = not math.isnan(th[2])
    has_l = not math.isnan(th[3])
    has_r = not math.isnan(th[4])
    a0 = th[2] if has_road else 0.0
    al = th[3] if has_l else 0.0
    ar = th[4] if has_r else 0.0
    a00 = a01 = a11 = b0 = b1 = inl = tot = 0.0
    r0 = r1 = r2 = r3 = l0 = l1 = l2 = l3 = q0 = q1 = q2 = q3 = 0.0
    for i in range(i0, i1):
        dxx = x[i] - xf
        dyy = y[i] - yf
        dn = dxx * nx[i] + dyy * ny[i]
        si = s[i]
        road_ok = has_road and dyy > margin
        left = dxx < 0.0
        adx = abs(dxx)
        a_s = al if left else ar
        side_ok = adx > margin and (has_l if left else has_r)
        pr = a0 * dn * dyy
        ps = a_s * dn * adx
        er = abs(si - pr) if road_ok else np.inf
        es = abs(si - ps) if side_ok else np.inf
        use_side = es < er  # road wins ties
        re = es if use_side else er
        pred = ps if use_side else pr
        valid = dn > 0.0 and re < np.inf and pred > 0.0
        u = re / (pred * c) if valid else 1.0
        wti = e[i] * g
        tot += wti if valid else 0.0
        inlier = u < 1.0
        inl += wti if inlier else 0.0
        v = 1.0 - u * u
        w = wti * v * v / (pred * pred) if inlier else 0.0
        sg = 1.0 if left else -1.0
        j0 = sg * a_s * (nx[i] * dxx + dn) if use_side else -a0 * nx[i] * dyy
        j1 = sg * a_s * ny[i] * dxx if use_side else -a0 * (ny[i] * dyy + dn)
        ja = dn * adx if use_side else dn * dyy
        wr = w * (si - pred)
        wj0 = w * j0
        wj1 = w * j1
        a00 += wj0 * j0
        a01 += wj0 * j1
        a11 += wj1 * j1
        b0 += wr * j0
        b1 += wr * j1
        c0 = wj0 * ja
        c1 = wj1 * ja
        c2 = w * ja * ja
        c3 = wr * ja
        mr = 0.0 if use_side else 1.0
        ml = 1.0 if use_side and left else 0.0
        mq = 1.0 if use_side and not left else 0.0
        r0 += mr * c0
        r1 += mr * c1
        r2 += mr * c2
        r3 += mr * c3
        l0 += ml * c0
        l1 += ml * c1
        l2 += ml * c2
        l3 += ml * c3
        q0 += mq * c0
        q1 += mq * c1
        q2 += mq * c2
        q3 += mq * c3
    return (a00, a01, a11, b0, b1, inl, tot, r0, r1, r2, r3, l0, l1, l2, l3, q0, q1, q2, q3)


@njit(cache=True, error_model="numpy")
def _normal_equations(sm, A, b):
    """The Gauss-Newton system from the sums of :func:`_sums` (J is 0 off each event's
    plane)."""
    A[:] = 0.0
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = sm[0], sm[1], sm[1], sm[2]
    b[0], b[1] = sm[3], sm[4]
    for k in range(3):  # per plane: w J0 Ja, w J1 Ja, w Ja Ja, w r Ja
        A[0, 2 + k] = A[2 + k, 0] = sm[7 + 4 * k]
        A[1, 2 + k] = A[2 + k, 1] = sm[8 + 4 * k]
        A[2 + k, 2 + k] = sm[9 + 4 * k]
        b[2 + k] = sm[10 + 4 * k]


@njit(cache=True, error_model="numpy")
def _condition(A, b):
    """Keep the scale of a plane without events (its row and column become the identity, no
    step) and add a 1e-9 ridge relative to the trace; False when the trace is not positive."""
    tr = 0.0
    for p in range(NP):
        tr += A[p, p]
    if not tr > 0.0:
        return False
    for p in range(NP):
        if A[p, p] <= 1e-12 * tr:  # a plane without events: keep its scale
            for q in range(NP):
                A[p, q] = 0.0
                A[q, p] = 0.0
            A[p, p] = 1.0
            b[p] = 0.0
        else:
            A[p, p] += 1e-9 * tr
    return True


@njit(cache=True, error_model="numpy")
def _apply_step(th, b, max_step):
    """th += the step b, the FOE's part shortened to ``max_step`` px; returns (the FOE step
    before shortening, px; every value finite, or NaN for a scale without a value)."""
    step = max(abs(b[0]), abs(b[1]))
    scale = 1.0 if step <= max_step else max_step / step
    for p in range(NP):
        th[p] += b[p] * (scale if p < 2 else 1.0)
    for p in range(NP):
        if not math.isfinite(th[p]) and not (p >= 2 and math.isnan(th[p])):
            return step, False
    return step, True


@njit(cache=True, error_model="numpy")
def fit(events, i0, i1, g, th, prm):
    """Fit the unknowns ``th`` to the events ``i0..i1``; robust Gauss-Newton (module docstring).

    NaN scales are initialised first. The events weigh ``e g``: ``e = exp((t - t_ref) / tau)``
    is kept per event (computed once), ``g = exp(-(T - t_ref) / tau)`` per fit, so an event at
    the fit time T weighs 1.

    Parameters
    ----------
    events : FitEvents
        float64 arrays: positions (px), unit normals, speeds (px/s, > 0), decay weights.
    i0, i1 : int
        The events fitted: ``i0 <= i < i1``.
    g : float
        The fit time's decay factor (see above).
    th : float64 ndarray, shape (5,)
        In/out: the FOE (px, entries :data:`FOE_X`, :data:`FOE_Y`) and the road's, left and
        right facades' scales (1/(s px): :data:`ROAD`, :data:`LEFT`, :data:`RIGHT`; NaN:
        unknown).
    prm : FitParams
        The constants.

    Returns
    -------
    (bool, float, float)
        ok (False when a system is singular or a value is not finite), the decayed inlier
        weight and the decayed weight of the events the model applies to.
    """
    x, y, nx, ny, s, e = events
    _init_scales(x, y, nx, ny, s, e, g, i0, i1, th, prm.margin)
    A = np.zeros((NP, NP))
    b = np.zeros(NP)
    inl = 0.0
    tot = 0.0
    for _ in range(prm.max_iter):
        sm = _sums(x, y, nx, ny, s, e, i0, i1, g, th, prm.margin, prm.tolerance)
        inl, tot = sm[5], sm[6]
        _normal_equations(sm, A, b)
        if not _condition(A, b) or not solve(A, b):
            return False, inl, tot
        step, finite = _apply_step(th, b, prm.max_step)
        if not finite:
            return False, inl, tot
        if step < 0.05:  # px: a warm-started fit moves less than this after 1-2 iterations
            break
    return True, inl, tot
