"""Numba kernels of ``plane_flow``: local plane fits on the surface of active events.

State: ``ts`` int64 ``[2, H, W]``, the latest timestamp per pixel and polarity (index 0 = OFF,
1 = ON), :data:`NO_EVENT` where a pixel has not fired yet. Every event updates its own pixel
(jAER's semantics); flow is computed for an event only if it is not inside the border margin and
not within ``refractory_us`` of the previous event at the same pixel and polarity.

Neighbours: same-polarity pixels of the ``(2r+1)^2`` window (the current pixel included, at
(0, 0, 0)) whose timestamp is valid and at most ``window_us`` old. Coordinates are centred on the
current event (pixels), times in seconds relative to it (<= 0).

Variants (``VARIANTS``): ``single`` (one closed-form least-squares fit of t = a x + b y + c),
``iterative`` (same, dropping points with |residual| > th2 s and refitting until the parameters
change < th1, giving up with <= 3 points left), ``robust`` (homogeneous plane n . (x, y, t) = d as
the smallest eigenvector of the points' covariance, iterated likewise, v from the gradient form),
``original`` (the same homogeneous iterative fit with jAER's per-component velocity
vx = -n_t / n_x, vy = -n_t / n_y, skipped when a component of the normal is exactly zero) and
``savitzky_golay`` (mean pairwise timestamp slope along rows -> dt/dx and along columns -> dt/dy).
Velocity everywhere except ``original``: v = g / |g|^2 with g = (dt/dx, dt/dy) in s/px.
Speed ceiling: flow with |v| > ``max_speed_pxs`` is rejected (th3 stated in px/s).
Singular or degenerate fits (collinear points, repeated eigenvalues, flat surfaces) are skipped:
no NaN or inf is ever written. The covariance and the 2x2 solve are :mod:`evchain.kernels.fit`'s.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from evchain.kernels.fit import centred_moments, smallest_eigvec3, sym2_det, sym2_solve

NO_EVENT = -(1 << 62)  # 'never fired': any age computed against it is huge, never overflows
SINGLE, ITERATIVE, ROBUST, ORIGINAL, SAVITZKY_GOLAY = range(5)
VARIANTS = {"single": SINGLE, "iterative": ITERATIVE, "robust": ROBUST, "original": ORIGINAL,
            "savitzky_golay": SAVITZKY_GOLAY}
# 1 - corr(x, y)^2 below this: points (numerically) collinear -> no plane. For integer pixel
# offsets a non-collinear set has at least 1 / (n^2 r^4) (~5e-6 for r = 3): well above.
COLLINEAR_EPS = 1e-9

#: why an event got no flow (indices of the kernel's ``counts``; the last counts the flow
#: events): within the refractory period, at the border, fewer neighbours than needed, the
#: neighbours too narrow (``min_spread``), no plane (degenerate or failed fit), the plane
#: misses the event (centre check), faster than the speed ceiling (a flat plane included)
WHY_NO_FLOW = ("refractory", "border", "too_few_neighbours", "too_narrow", "no_plane",
               "centre_check", "too_fast")
REFRACTORY, BORDER, TOO_FEW, TOO_NARROW, NO_PLANE, CENTRE, TOO_FAST, FLOW = range(8)


class PlaneParams(NamedTuple):
    """Constants of :func:`plane_flow_kernel`; built by ``records.record``."""

    variant: int              #: fit method, a value of :data:`VARIANTS`
    r: int                    #: half-width of the (2r+1)^2 neighbourhood, px
    window_us: int            #: neighbours at most this old, µs
    refractory_us: int        #: no flow this soon after the pixel's previous event, µs
    margin: int               #: no flow this close to the border, px
    min_points: int           #: fewest neighbours (the event included)
    th1: float                #: iterative fits: stop when the parameters change less
    th2: float                #: iterative fits' residual limit and centre check limit, s
    max_speed: float          #: drop faster flow, px/s
    max_iter: int             #: iterative fits: refits at most
    min_spread: float         #: neighbours' least spread across their principal axis, px
    centre_check: bool        #: drop a plane farther than th2 from the event itself
    max_window_us: int        #: speed-adaptive window up to this, µs (off when <= window_us)
    slow_px: float            #: adaptive window: the edge must move this far within it, px
    refit_failed: bool        #: adaptive window: also refit when the first fit fails
    refractory_updates: bool  #: a refractory event still updates the surface (jAER)
    min_window_us: int        #: shorter windows for fast edges down to this, µs (0: off)
    fast_px: float            #: short window: refit an edge that moved more than this, px


def new_state(width: int, height: int) -> np.ndarray:
    """The surface of active events, all pixels empty.

    Returns
    -------
    ts : int64 ndarray, shape (2, height, width)
        Latest timestamp (µs) per polarity (0 OFF, 1 ON) and pixel, :data:`NO_EVENT` for none.
    """
    return np.full((2, height, width), NO_EVENT, np.int64)


@njit(cache=True)
def fit_explicit(X, Y, T, use, n):
    """Least squares t = a x + b y + c over points with ``use``; (ok, a, b, c)."""
    m, mx, my, mt, cxx, cyy, _, cxy, cxt, cyt = centred_moments(X, Y, T, use, n)
    if m < 3:
        return False, 0.0, 0.0, 0.0
    det = sym2_det(cxx, cxy, cyy)
    if cxx <= 0.0 or cyy <= 0.0 or det <= COLLINEAR_EPS * cxx * cyy:
        return False, 0.0, 0.0, 0.0
    a, b = sym2_solve(cxx, cxy, cyy, cxt, cyt, det)
    c = mt - a * mx - b * my
    return True, a, b, c


@njit(cache=True)
def fit_homogeneous(X, Y, T, use, n):
    """Total least squares plane nx x + ny y + nt t = d; (ok, nx, ny, nt, d), |n| = 1."""
    m, mx, my, mt, cxx, cyy, ctt, cxy, cxt, cyt = centred_moments(X, Y, T, use, n)
    if m < 3:
        return False, 0.0, 0.0, 0.0, 0.0
    det = sym2_det(cxx, cxy, cyy)
    if cxx <= 0.0 or cyy <= 0.0 or det <= COLLINEAR_EPS * cxx * cyy:
        return False, 0.0, 0.0, 0.0, 0.0  # collinear in x-y: the plane may contain the t axis
    ok, nx, ny, nt = smallest_eigvec3(cxx, cxy, cxt, cyy, cyt, ctt)
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0
    return True, nx, ny, nt, nx * mx + ny * my + nt * mt


@njit(cache=True)
def iterate_explicit(X, Y, T, use, n, th1, th2, max_iter):
    """Iterative explicit fit; (ok, a, b, c)."""
    ok, a, b, c = fit_explicit(X, Y, T, use, n)
    if not ok:
        return False, 0.0, 0.0, 0.0
    for _ in range(max_iter):
        removed = 0
        left = 0
        for i in range(n):
            if use[i]:
                if abs(T[i] - (a * X[i] + b * Y[i] + c)) > th2:
                    use[i] = False
                    removed += 1
                else:
                    left += 1
        if removed == 0:
            break
        if left <= 3:
            return False, 0.0, 0.0, 0.0
        ok, a2, b2, c2 = fit_explicit(X, Y, T, use, n)
        if not ok:
            return False, 0.0, 0.0, 0.0
        change = max(abs(a2 - a), abs(b2 - b), abs(c2 - c))
        a, b, c = a2, b2, c2
        if change < th1:
            break
    return True, a, b, c


@njit(cache=True)
def iterate_homogeneous(X, Y, T, use, n, th1, th2, max_iter):
    """Iterative homogeneous fit; (ok, nx, ny, nt, d)."""
    ok, nx, ny, nt, d = fit_homogeneous(X, Y, T, use, n)
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0
    for _ in range(max_iter):
        removed = 0
        left = 0
        for i in range(n):
            if use[i]:
                if abs(nx * X[i] + ny * Y[i] + nt * T[i] - d) > th2:
                    use[i] = False
                    removed += 1
                else:
                    left += 1
        if removed == 0:
            break
        if left <= 3:
            return False, 0.0, 0.0, 0.0, 0.0
        ok, nx2, ny2, nt2, d2 = fit_homogeneous(X, Y, T, use, n)
        if not ok:
            return False, 0.0, 0.0, 0.0, 0.0
        change = max(abs(nx2 - nx), abs(ny2 - ny), abs(nt2 - nt))
        nx, ny, nt, d = nx2, ny2, nt2, d2
        if change < th1:
            break
    return True, nx, ny, nt, d


@njit(cache=True)
def sg_gradient(wt, wv, size):
    """Mean pairwise timestamp slopes along rows and columns of the window (s/px).

    ``wt``: the window's timestamps relative to the event (µs as float64, 0 where invalid),
    ``wv`` its validity as 0.0/1.0, both row-major ``size x size``. Branch-free: pair
    differences are summed per distance d (exact: whole µs), then weighted by 1/d.
    (ok, gx, gy); ok needs a pair in each direction.
    """
    gx = 0.0
    gy = 0.0
    nx = 0.0
    ny = 0.0
    for d in range(1, size):  # rows: pairs (line, a) - (line, a + d)
        sd = 0.0
        for line in range(size):
            base = line * size
            for a in range(size - d):
                ka = base + a
                both = wv[ka] * wv[ka + d]
                sd += both * (wt[ka + d] - wt[ka])
                nx += both
        gx += sd / d
    for d in range(1, size):  # columns: pairs k - (k + d size), contiguous in k
        sd = 0.0
        step = d * size
        for ka in range((size - d) * size):
            both = wv[ka] * wv[ka + step]
            sd += both * (wt[ka + step] - wt[ka])
            ny += both
        gy += sd / d
    if nx == 0.0 or ny == 0.0:
        return False, 0.0, 0.0
    return True, gx * 1e-6 / nx, gy * 1e-6 / ny


#: widest window (2r+1) whose Savitzky-Golay slopes use the per-row mask table
SG_TABLE_MAX_SIZE = 7
#: common multiple of the pair distances 1..SG_TABLE_MAX_SIZE-1: table coefficients are integers
SG_SCALE = 60.0


@njit(cache=True, inline="always")
def _pair_coefficient(m, b, size):
    """coef[m, b] of :func:`sg_tables` for a valid b."""
    acc = 0.0
    for a in range(size):
        if a != b and (m >> a) & 1:
            w = SG_SCALE / abs(b - a)
            acc += w if a < b else -w
    return acc


@njit(cache=True)
def sg_tables(size):
    """Per-line tables of the mean pairwise slope for every validity mask of a line of ``size``.

    For a line with validity bits ``m`` the sum over valid pairs a < b of (t_b - t_a) / (b - a)
    equals sum_b coef[m, b] t_b with coef[m, b] = sum_{a<b valid} 1/(b-a) - sum_{c>b valid}
    1/(c-b) (b valid, else 0); stored scaled by :data:`SG_SCALE` (integers, exact).
    ``pairs[m]``: number of valid pairs. Returns (coef float64[2^size, size], pairs float64)."""
    nm = 1 << size
    coef = np.zeros((nm, size), np.float64)
    pairs = np.zeros(nm, np.float64)
    for m in range(nm):
        c = 0
        for b in range(size):
            if (m >> b) & 1:
                c += 1
                coef[m, b] = _pair_coefficient(m, b, size)
        pairs[m] = c * (c - 1) // 2
    return coef, pairs


@njit(cache=True)
def sg_gradient_masks(wt, rowmask, colmask, size, coef, pairs):
    """:func:`sg_gradient` from per-row and per-column validity masks and the tables of
    :func:`sg_tables` (same result up to rounding: the scaled coefficients and the µs times are
    integers, so the sums are exact)."""
    gx = 0.0
    gy = 0.0
    nx = 0.0
    ny = 0.0
    for line in range(size):
        m = rowmask[line]
        if pairs[m] > 0.0:
            nx += pairs[m]
            base = line * size
            for b in range(size):
                gx += coef[m, b] * wt[base + b]
        m = colmask[line]
        if pairs[m] > 0.0:
            ny += pairs[m]
            for b in range(size):
                gy += coef[m, b] * wt[b * size + line]
    if nx == 0.0 or ny == 0.0:
        return False, 0.0, 0.0
    return True, gx * (1e-6 / SG_SCALE) / nx, gy * (1e-6 / SG_SCALE) / ny


#: refits of the adaptive window at most (the window only grows, so this bounds the work)
MAX_REFITS = 4


@njit(cache=True, inline="always")
def _mask_counts(n_masks, size, r):
    """Per validity mask of a line of ``size`` pixels: its number of valid pixels and the sum of
    their offsets from the centre (int64[n_masks] each). Inlined: allocated in the loop's
    function, the compiler knows the tables alias nothing (returned by a call, the loop was
    slower)."""
    popcount = np.zeros(n_masks, np.int64)
    bitsum = np.zeros(n_masks, np.int64)
    for m in range(n_masks):
        for b in range(size):
            if (m >> b) & 1:
                popcount[m] += 1
                bitsum[m] += b - r
    return popcount, bitsum


@njit(cache=True, inline="always")
def _gets_flow(xi, yi, width, height, margin, r, variant):
    """Outside the border margin (and, for Savitzky-Golay, with the whole stencil inside)."""
    if xi < margin or yi < margin or xi >= width - margin or yi >= height - margin:
        return False
    full = xi >= r and yi >= r and xi + r < width and yi + r < height
    return variant != SAVITZKY_GOLAY or full  # SG needs the whole stencil (border_px < r)


@njit(cache=True, inline="always")
def _next_window(ok, gx, gy, w, window_us, max_window_us, refit_failed, k_us):
    """Adaptive window: the window to refit with after a fit with window ``w`` (µs) gave
    gradient (gx, gy) (s/px; ``ok`` False: no fit); ``w`` itself when there is no refit."""
    if ok:
        want = k_us * math.sqrt(gx * gx + gy * gy)
        if want <= w:
            return w  # the edge moved at least slow_px within the window
        return max_window_us if want >= max_window_us else np.int64(want)
    if refit_failed and w == window_us:
        return max_window_us
    return w


@njit(cache=True, inline="always")
def _mask_moments(rowmask, size, r, spread2):
    """Sums of dx dx, dy dy, dx dy over the valid pixels of the row masks (0 unless
    ``spread2`` > 0: only the spread test needs them)."""
    sxx = 0
    syy = 0
    sxy = 0
    if not spread2 > 0.0:
        return sxx, syy, sxy
    for kk in range(size * size):
        if (rowmask[kk // size] >> (kk % size)) & 1:
            dx = kk % size - r
            dy = kk // size - r
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
    return sxx, syy, sxy


@njit(cache=True, inline="always")
def _window_moments(wv, size, r, spread2):
    """Sums of dx dx, dy dy, dx dy over the valid pixels of the window's validity ``wv`` (0
    unless ``spread2`` > 0)."""
    sxx = 0
    syy = 0
    sxy = 0
    if not spread2 > 0.0:
        return sxx, syy, sxy
    for kk in range(size * size):
        if wv[kk] > 0.0:
            dx = kk % size - r
            dy = kk // size - r
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
    return sxx, syy, sxy


@njit(cache=True, inline="always")
def _gather_masks(ts, pi, xi, yi, ti, w, r, wt, rowmask, colmask, popcount, bitsum, spread2):
    """Savitzky-Golay with the mask tables: the window's times ``wt`` (µs before the event) and
    validity masks per row and column. Returns (n, st, sx, sy, sxx, syy, sxy): the number of
    valid pixels, the sum of their times (µs, <= 0) and of their offsets and (only with
    ``spread2``) products of offsets."""
    size = 2 * r + 1
    n = 0
    st = 0.0
    sx = 0
    sy = 0
    for dy in range(-r, r + 1):
        row = ts[pi, yi + dy]
        k0 = (dy + r) * size + r
        rm = 0
        for dx in range(-r, r + 1):
            age = ti - row[xi + dx]
            # invalid times stay in wt: the tables give them weight 0
            wt[k0 + dx] = -age
            valid = np.int64(age <= w)  # branch-free: validity is unpredictable
            st -= age * valid
            rm |= valid << (dx + r)
        rowmask[dy + r] = rm
        n += popcount[rm]
        sx += bitsum[rm]
        sy += dy * popcount[rm]
    for c in range(size):
        cm = 0
        for line in range(size):
            cm |= ((rowmask[line] >> c) & 1) << line
        colmask[c] = cm
    sxx, syy, sxy = _mask_moments(rowmask, size, r, spread2)
    return n, st, sx, sy, sxx, syy, sxy


@njit(cache=True, inline="always")
def _gather_window(ts, pi, xi, yi, ti, w, r, wt, wv, spread2):
    """Savitzky-Golay on a window too wide for the tables: its times ``wt`` (µs before the
    event, 0 where invalid) and validity ``wv``; returns as :func:`_gather_masks`."""
    size = 2 * r + 1
    n = 0
    st = 0.0
    sx = 0
    sy = 0
    for dy in range(-r, r + 1):
        row = ts[pi, yi + dy]
        k0 = (dy + r) * size + r
        for dx in range(-r, r + 1):
            age = ti - row[xi + dx]
            valid = 1 if age <= w else 0
            wv[k0 + dx] = valid
            wt[k0 + dx] = -age * valid
            st -= age * valid
            n += valid
            sx += dx * valid
            sy += dy * valid
    sxx, syy, sxy = _window_moments(wv, size, r, spread2)
    return n, st, sx, sy, sxx, syy, sxy


@njit(cache=True, inline="always")
def _gather_points(ts, pi, xi, yi, ti, w, r, X, Y, T, use):
    """The valid neighbours as points (the event itself included; branch-free): the first n
    entries of ``X``, ``Y`` (px), ``T`` (s, <= 0). Returns as :func:`_gather_masks` (st 0)."""
    height = ts.shape[1]
    width = ts.shape[2]
    n = 0
    sx = 0
    sy = 0
    sxx = 0
    syy = 0
    sxy = 0
    for dy in range(-r, r + 1):
        yy = yi + dy
        if yy < 0 or yy >= height:
            continue
        row = ts[pi, yy]
        for dx in range(-r, r + 1):
            xx = xi + dx
            if xx < 0 or xx >= width:
                continue
            age = ti - row[xx]
            valid = 1 if age <= w else 0
            X[n] = dx
            Y[n] = dy
            T[n] = -age * 1e-6
            use[n] = True
            n += valid
            sx += dx * valid
            sy += dy * valid
            sxx += dx * dx * valid
            syy += dy * dy * valid
            sxy += dx * dy * valid
    return n, 0.0, sx, sy, sxx, syy, sxy


@njit(cache=True, inline="always")
def _spread_at_least(n, sx, sy, sxx, syy, sxy, spread2):
    """Whether the points' position covariance has its smallest eigenvalue >= ``spread2``
    (px^2): n^2 (cov - spread2 I) = [[a, b], [b, c]] - s must be positive semi-definite. The
    sums are of integer offsets, so a, b, c are exact and a tie on the bound is decided the
    same by every order of summation."""
    s = n * n * spread2
    a = n * sxx - sx * sx - s
    c = n * syy - sy * sy - s
    b = n * sxy - sx * sy
    return a >= 0.0 and c >= 0.0 and a * c >= b * b


@njit(cache=True, inline="always")
def _centre_ok(fit_ok, c, lim, centre_check):
    """A fit is kept when it succeeded and, with the centre check, its plane passes within
    ``lim`` (s) of the event (``c``: the plane's time at the event, s)."""
    return fit_ok and not (centre_check and abs(c) > lim)


@njit(cache=True, inline="always")
def _normal_gradient(fit_ok, nx, ny, nt, d, lim, centre_check, original):
    """(ok, gx, gy) from a homogeneous plane n . (x, y, t) = d: the gradient -(nx, ny) / nt
    (s/px), or with ``original`` jAER's velocity -nt / (nx, ny) (px/s)."""
    if not fit_ok or nt <= 0.0 or (centre_check and abs(d) > lim):
        return False, 0.0, 0.0
    if original:
        if nx == 0.0 or ny == 0.0:
            return False, 0.0, 0.0
        return True, -nt / nx, -nt / ny
    return True, -nx / nt, -ny / nt


@njit(cache=True, inline="always")
def _velocity(variant, gx, gy, max_speed, g_min2):
    """Flow (ok, vx, vy) in px/s from the gradient (s/px): v = g / |g|^2 (``original``: g is the
    velocity); not ok above the speed ceiling or for a flat plane."""
    if variant == ORIGINAL:
        if gx * gx + gy * gy > max_speed * max_speed:
            return False, 0.0, 0.0
        return True, gx, gy
    g2 = gx * gx + gy * gy
    if g2 < g_min2 or g2 == 0.0:
        return False, 0.0, 0.0
    return True, gx / g2, gy / g2


#: how a fit gathers its window: Savitzky-Golay with the mask tables, Savitzky-Golay on a wide
#: window, or the valid neighbours as points (the other variants)
MASKS, WINDOW, POINTS = range(3)


@njit(cache=True)
def _gather_mode(variant, r):
    """The gather of a variant and search distance (:data:`MASKS`, :data:`WINDOW` or
    :data:`POINTS`)."""
    if variant != SAVITZKY_GOLAY:
        return POINTS
    return MASKS if 2 * r + 1 <= SG_TABLE_MAX_SIZE else WINDOW


@njit(cache=True, inline="always")
def event_loop(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts, adaptive, gather):
    """The loop of :func:`plane_flow_kernel`: the speed-adaptive window's refits with
    ``adaptive``, the fits' gather ``gather`` (:func:`_gather_mode`). Inlined into the kernels
    with both constant, so that each copy of the loop compiles only its own gather and fits
    (and the fixed window's copies no refits): a loop choosing among inlined gathers per event
    kept their work arrays' reference counts in the loop; called gathers cost a call per fit."""
    height = ts.shape[1]
    width = ts.shape[2]
    variant = prm.variant
    r = prm.r
    size = 2 * r + 1
    # scratch (allocated here: the compiler then knows they alias nothing): the points X, Y
    # (px), T (s) and their flags; the window's times (µs) and validity; its masks per line
    cap = size * size
    X = np.empty(cap, np.float64)
    Y = np.empty(cap, np.float64)
    T = np.empty(cap, np.float64)
    use = np.empty(cap, np.bool_)
    wt = np.empty(cap, np.float64)
    wv = np.empty(cap, np.float64)
    rowmask = np.zeros(size, np.int64)
    colmask = np.zeros(size, np.int64)
    coef, pairs = sg_tables(size if gather == MASKS else 1)
    popcount, bitsum = _mask_counts(coef.shape[0], size, r)
    g_min2 = 1.0 / (prm.max_speed * prm.max_speed)
    spread2 = prm.min_spread * prm.min_spread
    k_us = prm.slow_px * 1e6  # W (µs) = k_us |g| (s/px): the window in which the edge moves k px
    kf_us = prm.fast_px * 1e6
    shorten = adaptive and 0 < prm.min_window_us < prm.window_us
    fits = MAX_REFITS + 1 if adaptive else 1
    n_out = 0
    for i in range(len(x)):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        ti = t[i]
        pi = 1 if p[i] > 0 else 0
        prev = ts[pi, yi, xi]
        refractory = prev != NO_EVENT and ti - prev < prm.refractory_us
        if not refractory or prm.refractory_updates:
            ts[pi, yi, xi] = ti
        if refractory:
            counts[REFRACTORY] += 1
            continue
        if not _gets_flow(xi, yi, width, height, prm.margin, r, variant):
            counts[BORDER] += 1
            continue
        # fits with window w (µs) and residual / centre check limit lim (s); a failed fit
        # continues with the next, whose start decides whether to refit
        w, lim, ok, gx, gy = prm.window_us, prm.th2, False, 0.0, 0.0
        shrunk, g0x, g0y = False, 0.0, 0.0
        why = NO_PLANE  # the last fit's failure
        for k in range(fits):
            if k > 0:  # adaptive: refit when the last fit asks for a longer window
                w_new = _next_window(ok, gx, gy, w, prm.window_us, prm.max_window_us,
                                     prm.refit_failed, k_us)
                if k == 1 and shorten and ok:
                    w_short = kf_us * math.sqrt(gx * gx + gy * gy)
                    if w_short < w:  # the edge moved more than fast_px: a shorter window
                        w_s = max(np.int64(prm.min_window_us), np.int64(math.ceil(w_short)))
                        if w_s < w:
                            w_new, shrunk, g0x, g0y = w_s, True, gx, gy
                if w_new <= w and not shrunk:
                    break
                if k > 1 and shrunk:
                    break
                w = w_new
                lim = prm.th2 * w / prm.window_us
            if gather == MASKS:
                n, st, sx, sy, sxx, syy, sxy = _gather_masks(ts, pi, xi, yi, ti, w, r, wt,
                                                             rowmask, colmask, popcount,
                                                             bitsum, spread2)
            elif gather == WINDOW:
                n, st, sx, sy, sxx, syy, sxy = _gather_window(ts, pi, xi, yi, ti, w, r, wt, wv,
                                                              spread2)
            else:
                n, st, sx, sy, sxx, syy, sxy = _gather_points(ts, pi, xi, yi, ti, w, r, X, Y, T,
                                                              use)
            ok = False
            if n < prm.min_points or n < 3:
                why = TOO_FEW
                continue
            if spread2 > 0.0 and not _spread_at_least(n, sx, sy, sxx, syy, sxy, spread2):
                why = TOO_NARROW
                continue
            why = NO_PLANE
            # (gx, gy): the gradient (dt/dx, dt/dy) in s/px; for original its velocity
            if gather == MASKS:
                ok, gx, gy = sg_gradient_masks(wt, rowmask, colmask, size, coef, pairs)
            elif gather == WINDOW:
                ok, gx, gy = sg_gradient(wt, wv, size)
            elif variant == SINGLE:
                fit_ok, gx, gy, c = fit_explicit(X, Y, T, use, n)
                ok = _centre_ok(fit_ok, c, lim, prm.centre_check)
                if fit_ok and not ok:
                    why = CENTRE
            elif variant == ITERATIVE:
                fit_ok, gx, gy, c = iterate_explicit(X, Y, T, use, n, prm.th1, lim, prm.max_iter)
                ok = _centre_ok(fit_ok, c, lim, prm.centre_check)
                if fit_ok and not ok:
                    why = CENTRE
            else:
                fit_ok, nx, ny, nt, d = iterate_homogeneous(X, Y, T, use, n, prm.th1, lim,
                                                            prm.max_iter)
                ok, gx, gy = _normal_gradient(fit_ok, nx, ny, nt, d, lim, prm.centre_check,
                                              variant == ORIGINAL)
                if fit_ok and nt > 0.0 and prm.centre_check and abs(d) > lim:
                    why = CENTRE
            if gather != POINTS and ok and prm.centre_check:
                # the plane with these slopes through the points' centroid, at the event
                ok = not abs((st * 1e-6 - gx * sx - gy * sy) / n) > lim
                if not ok:
                    why = CENTRE
        if shrunk and not ok:  # the shorter window gave no estimate: the first one stands
            ok, gx, gy = True, g0x, g0y
        if not ok:
            counts[why] += 1
            continue
        ok, vx, vy = _velocity(variant, gx, gy, prm.max_speed, g_min2)
        counts[FLOW if ok else TOO_FAST] += 1
        if ok:
            out_idx[n_out] = i
            out_vx[n_out] = vx
            out_vy[n_out] = vy
            n_out += 1
    return n_out


@njit(cache=True, nogil=True)
def plane_flow_adaptive_kernel(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts):
    """:func:`plane_flow_kernel` with the speed-adaptive window (the loop with the refits); the
    same arguments and result."""
    gather = _gather_mode(prm.variant, prm.r)
    if gather == MASKS:
        return event_loop(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts, True, MASKS)
    if gather == WINDOW:
        return event_loop(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts, True, WINDOW)
    return event_loop(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts, True, POINTS)


@njit(cache=True, nogil=True)
def plane_flow_kernel(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts):
    """Process events in order, updating ``ts`` in place; returns the number of flow events.

    ``prm.min_spread`` (px): the neighbours' positions must spread at least this much (standard
    deviation) across their principal direction, 0 = off (jAER). ``prm.centre_check``: drop the
    estimate when the event itself lies farther than ``th2`` (s) from the final plane (the plane
    then describes other, older structure).

    Speed-adaptive window (on when ``max_window_us > window_us``; not for ``original``): when
    the fit with ``window_us`` says the edge moved less than ``slow_px`` px within the window
    (or, with ``refit_failed``, gives no estimate), refit with the window in which it would
    move ``slow_px`` px, W = slow_px |g|, at most ``max_window_us`` (the longest when there
    is no estimate); repeat while the window grows (at most :data:`MAX_REFITS` refits). A
    refit's centre check limit (and the iterative fits' residual limit) is ``th2 W / window_us``
    (the same fraction of the time per pixel). The last fit is the result; a failed refit gives
    no flow. Runs :func:`plane_flow_adaptive_kernel`.

    Short window (on when 0 < ``min_window_us`` < ``window_us``; not for ``original``): a first
    fit whose edge moved more than ``fast_px`` px within ``window_us`` is redone with the window
    in which it moves ``fast_px``, W = fast_px |g|, at least ``min_window_us``, instead of any
    longer refit; when that fit fails the first one stands. Also runs
    :func:`plane_flow_adaptive_kernel`.

    ``refractory_updates`` (jAER: true): an event within ``refractory_us`` still updates the
    surface; false: it is dropped entirely (the thesis's description), so the surface holds the
    onset of each pixel's burst and the refractory period counts from the last onset.

    Parameters
    ----------
    x, y : uint16 ndarray, shape (n,)
        Pixel coordinates of the events, in time order.
    t : int64 ndarray, shape (n,)
        Timestamps, µs, non-decreasing.
    p : int8 ndarray, shape (n,)
        Polarities (> 0: ON).
    ts : int64 ndarray, shape (2, H, W)
        The surface of active events (:func:`new_state`), updated in place.
    prm : PlaneParams
        The constants.
    out_idx : int64 ndarray, shape (>= n,)
        Out: indices of the events with flow.
    out_vx, out_vy : float64 ndarray, shape (>= n,)
        Out: their flow, px/s.
    counts : int64 ndarray, shape (8,)
        Added to: per event, why it got no flow (:data:`WHY_NO_FLOW`, the last fit's reason
        where there were refits) or, last, that it got flow.

    Returns
    -------
    int
        The number of events with flow (the filled length of ``out_*``).
    """
    if (prm.max_window_us > prm.window_us or 0 < prm.min_window_us < prm.window_us) \
            and prm.variant != ORIGINAL:
        return plane_flow_adaptive_kernel(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts)
    gather = _gather_mode(prm.variant, prm.r)
    if gather == MASKS:
        return event_loop(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts, False, MASKS)
    if gather == WINDOW:
        return event_loop(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts, False, WINDOW)
    return event_loop(x, y, t, p, ts, prm, out_idx, out_vx, out_vy, counts, False, POINTS)
