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
no NaN or inf is ever written.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

NO_EVENT = -(1 << 62)  # 'never fired': any age computed against it is huge, never overflows
VARIANTS = {"single": 0, "iterative": 1, "robust": 2, "original": 3, "savitzky_golay": 4}
# 1 - corr(x, y)^2 below this: points (numerically) collinear -> no plane. For integer pixel
# offsets a non-collinear set has at least 1 / (n^2 r^4) (~5e-6 for r = 3): well above.
COLLINEAR_EPS = 1e-9
# two smallest eigenvalues closer than this (relative to the largest): normal undefined.
EIG_EPS = 1e-12


def new_state(width: int, height: int) -> np.ndarray:
    """The surface of active events, all pixels empty."""
    return np.full((2, height, width), NO_EVENT, np.int64)


@njit(cache=True)
def fit_explicit(X, Y, T, use, n):
    """Least squares t = a x + b y + c over points with ``use``; (ok, a, b, c)."""
    m = 0
    sx = 0.0
    sy = 0.0
    st = 0.0
    for i in range(n):
        if use[i]:
            m += 1
            sx += X[i]
            sy += Y[i]
            st += T[i]
    if m < 3:
        return False, 0.0, 0.0, 0.0
    mx = sx / m
    my = sy / m
    mt = st / m
    cxx = 0.0
    cyy = 0.0
    cxy = 0.0
    cxt = 0.0
    cyt = 0.0
    for i in range(n):
        if use[i]:
            dx = X[i] - mx
            dy = Y[i] - my
            dt = T[i] - mt
            cxx += dx * dx
            cyy += dy * dy
            cxy += dx * dy
            cxt += dx * dt
            cyt += dy * dt
    det = cxx * cyy - cxy * cxy
    if cxx <= 0.0 or cyy <= 0.0 or det <= COLLINEAR_EPS * cxx * cyy:
        return False, 0.0, 0.0, 0.0
    a = (cyy * cxt - cxy * cyt) / det
    b = (cxx * cyt - cxy * cxt) / det
    c = mt - a * mx - b * my
    return True, a, b, c


@njit(cache=True)
def smallest_eigvec3(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (cyclic Jacobi).

    Jacobi rotations give eigenvalues to about eps * |A| absolutely, so a small eigenvalue stays
    separable from its neighbour even when one eigenvalue dominates (a closed-form cubic solver
    loses ~sqrt(eps) there). Returns (ok, v0, v1, v2) with v2 >= 0; not ok when the smallest
    eigenvalue is (numerically) repeated.
    """
    A = np.empty((3, 3))
    A[0, 0] = a00
    A[0, 1] = a01
    A[0, 2] = a02
    A[1, 0] = a01
    A[1, 1] = a11
    A[1, 2] = a12
    A[2, 0] = a02
    A[2, 1] = a12
    A[2, 2] = a22
    V = np.eye(3)
    scale = a00 * a00 + a11 * a11 + a22 * a22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    if scale <= 0.0:
        return False, 0.0, 0.0, 0.0
    for _ in range(30):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        if off <= 1e-34 * scale:
            break
        for p in range(2):
            for q in range(p + 1, 3):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                tt = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    tt = -tt
                c = 1.0 / math.sqrt(tt * tt + 1.0)
                s = tt * c
                for k in range(3):  # A <- A J (columns p, q)
                    akp = A[k, p]
                    akq = A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(3):  # A <- J^T A (rows p, q)
                    apk = A[p, k]
                    aqk = A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                for k in range(3):
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    e0 = A[0, 0]
    e1 = A[1, 1]
    e2 = A[2, 2]
    j = 0
    if e1 < e0 and e1 <= e2:
        j = 1
    elif e2 < e0 and e2 < e1:
        j = 2
    lo = A[j, j]
    nxt = np.inf
    big = -np.inf
    for k in range(3):
        if k != j:
            nxt = min(nxt, A[k, k])
        big = max(big, abs(A[k, k]))
    if nxt - lo <= EIG_EPS * big:
        return False, 0.0, 0.0, 0.0
    v0 = V[0, j]
    v1 = V[1, j]
    v2 = V[2, j]
    nn = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    v0 /= nn
    v1 /= nn
    v2 /= nn
    if v2 < 0.0:  # sign convention: normal with n_t >= 0
        v0, v1, v2 = -v0, -v1, -v2
    return True, v0, v1, v2


@njit(cache=True)
def fit_homogeneous(X, Y, T, use, n):
    """Total least squares plane nx x + ny y + nt t = d; (ok, nx, ny, nt, d), |n| = 1."""
    m = 0
    sx = 0.0
    sy = 0.0
    st = 0.0
    for i in range(n):
        if use[i]:
            m += 1
            sx += X[i]
            sy += Y[i]
            st += T[i]
    if m < 3:
        return False, 0.0, 0.0, 0.0, 0.0
    mx = sx / m
    my = sy / m
    mt = st / m
    cxx = 0.0
    cyy = 0.0
    ctt = 0.0
    cxy = 0.0
    cxt = 0.0
    cyt = 0.0
    for i in range(n):
        if use[i]:
            dx = X[i] - mx
            dy = Y[i] - my
            dt = T[i] - mt
            cxx += dx * dx
            cyy += dy * dy
            ctt += dt * dt
            cxy += dx * dy
            cxt += dx * dt
            cyt += dy * dt
    det = cxx * cyy - cxy * cxy
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
                acc = 0.0
                for a in range(size):
                    if a != b and (m >> a) & 1:
                        w = SG_SCALE / abs(b - a)
                        acc += w if a < b else -w
                coef[m, b] = acc
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
def event_loop(x, y, t, p, ts, variant, r, window_us, refractory_us, margin, min_points, th1,
               th2, max_speed, max_iter, min_spread, centre_check, out_idx, out_vx, out_vy,
               max_window_us, slow_px, refit_failed, refractory_updates, adaptive):
    """The loop of :func:`plane_flow_kernel`; the speed-adaptive window's refits with
    ``adaptive``. Inlined into each kernel with ``adaptive`` a constant, so that the fixed
    window's loop compiles without the refits. The fit is written out in the loop, not called:
    a (numba-inlined) function taking the work arrays costs their reference counts per event,
    a large share of the fixed window's time."""
    height = ts.shape[1]
    width = ts.shape[2]
    size = 2 * r + 1
    cap = size * size
    X = np.empty(cap, np.float64)
    Y = np.empty(cap, np.float64)
    T = np.empty(cap, np.float64)
    use = np.empty(cap, np.bool_)
    wt = np.empty(cap, np.float64)
    wv = np.empty(cap, np.float64)
    rowmask = np.zeros(size, np.int64)
    colmask = np.zeros(size, np.int64)
    tabulated = variant == 4 and size <= SG_TABLE_MAX_SIZE
    if tabulated:
        coef, pairs = sg_tables(size)
    else:
        coef, pairs = sg_tables(1)
    # per line mask: number of valid pixels and the sum of their offsets from the centre
    popcount = np.zeros(coef.shape[0], np.int64)
    bitsum = np.zeros(coef.shape[0], np.int64)
    for m in range(coef.shape[0]):
        for b in range(size):
            if (m >> b) & 1:
                popcount[m] += 1
                bitsum[m] += b - r
    g_min2 = 1.0 / (max_speed * max_speed)
    spread2 = min_spread * min_spread
    k_us = slow_px * 1e6  # W (µs) = k_us |g| (s/px): the window in which the edge moves k px
    fits = MAX_REFITS + 1 if adaptive else 1
    n_out = 0
    for i in range(len(x)):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        ti = t[i]
        pi = 1 if p[i] > 0 else 0
        prev = ts[pi, yi, xi]
        if prev != NO_EVENT and ti - prev < refractory_us:
            if refractory_updates:
                ts[pi, yi, xi] = ti
            continue
        ts[pi, yi, xi] = ti
        if xi < margin or yi < margin or xi >= width - margin or yi >= height - margin:
            continue
        full = xi >= r and yi >= r and xi + r < width and yi + r < height
        if variant == 4 and not full:
            continue  # SG needs the whole stencil (border_px < r)
        # fits with window w (µs) and residual / centre check limit lim (s); a failed fit
        # continues with the next, whose start decides whether to refit
        w = window_us
        lim = th2
        ok = False
        gx = 0.0
        gy = 0.0
        for k in range(fits):
            if k > 0:  # adaptive: refit when the last fit asks for a longer window
                if ok:
                    want = k_us * math.sqrt(gx * gx + gy * gy)
                    if want <= w:
                        break  # the edge moved at least slow_px within the window
                    w_new = max_window_us if want >= max_window_us else np.int64(want)
                elif refit_failed and w == window_us:
                    w_new = max_window_us
                else:
                    break
                if w_new <= w:
                    break
                w = w_new
                lim = th2 * w / window_us
            ok = False
            n = 0
            st = 0.0
            sx = 0
            sy = 0
            sxx = 0
            syy = 0
            sxy = 0
            if tabulated:  # SG: the window's times and validity masks per row and column
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
                if spread2 > 0.0:
                    for kk in range(cap):
                        if (rowmask[kk // size] >> (kk % size)) & 1:
                            dx = kk % size - r
                            dy = kk // size - r
                            sxx += dx * dx
                            syy += dy * dy
                            sxy += dx * dy
            elif variant == 4:  # SG, wide window: only the window's times and validity
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
                if spread2 > 0.0:
                    for kk in range(cap):
                        if wv[kk] > 0.0:
                            dx = kk % size - r
                            dy = kk // size - r
                            sxx += dx * dx
                            syy += dy * dy
                            sxy += dx * dy
            else:  # the valid neighbours as points (the event itself included), branch-free
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
            if n < min_points or n < 3:
                continue
            if spread2 > 0.0:
                cxx = (sxx - sx * sx / n) / n
                cyy = (syy - sy * sy / n) / n
                cxy = (sxy - sx * sy / n) / n
                half = 0.5 * (cxx + cyy)
                lam = half - math.sqrt(max(0.25 * (cxx - cyy) ** 2 + cxy * cxy, 0.0))
                if lam < spread2:
                    continue
            # (gx, gy): the gradient (dt/dx, dt/dy) in s/px; for original its velocity
            if variant == 4:
                if tabulated:
                    fit_ok, gx, gy = sg_gradient_masks(wt, rowmask, colmask, size, coef, pairs)
                else:
                    fit_ok, gx, gy = sg_gradient(wt, wv, size)
                if not fit_ok:
                    continue
                # the plane with these slopes through the points' centroid, at the event
                c = (st * 1e-6 - gx * sx - gy * sy) / n
                if centre_check and abs(c) > lim:
                    continue
            elif variant == 0:
                fit_ok, gx, gy, c = fit_explicit(X, Y, T, use, n)
                if not fit_ok or (centre_check and abs(c) > lim):
                    continue
            elif variant == 1:
                fit_ok, gx, gy, c = iterate_explicit(X, Y, T, use, n, th1, lim, max_iter)
                if not fit_ok or (centre_check and abs(c) > lim):
                    continue
            else:
                fit_ok, nx, ny, nt, d = iterate_homogeneous(X, Y, T, use, n, th1, lim,
                                                            max_iter)
                if not fit_ok or nt <= 0.0 or (centre_check and abs(d) > lim):
                    continue
                if variant == 3:
                    if nx == 0.0 or ny == 0.0:
                        continue
                    gx = -nt / nx
                    gy = -nt / ny
                else:
                    gx = -nx / nt
                    gy = -ny / nt
            ok = True
        if not ok:
            continue
        if variant == 3:
            if gx * gx + gy * gy > max_speed * max_speed:
                continue
            out_idx[n_out] = i
            out_vx[n_out] = gx
            out_vy[n_out] = gy
            n_out += 1
            continue
        g2 = gx * gx + gy * gy
        if g2 < g_min2 or g2 == 0.0:
            continue
        out_idx[n_out] = i
        out_vx[n_out] = gx / g2
        out_vy[n_out] = gy / g2
        n_out += 1
    return n_out


@njit(cache=True)
def plane_flow_adaptive_kernel(x, y, t, p, ts, variant, r, window_us, refractory_us, margin,
                               min_points, th1, th2, max_speed, max_iter, min_spread,
                               centre_check, out_idx, out_vx, out_vy, max_window_us, slow_px,
                               refit_failed, refractory_updates):
    """:func:`plane_flow_kernel` with the speed-adaptive window (the loop with the refits)."""
    return event_loop(x, y, t, p, ts, variant, r, window_us, refractory_us, margin, min_points,
                      th1, th2, max_speed, max_iter, min_spread, centre_check, out_idx, out_vx,
                      out_vy, max_window_us, slow_px, refit_failed, refractory_updates, True)


@njit(cache=True)
def plane_flow_kernel(x, y, t, p, ts, variant, r, window_us, refractory_us, margin,
                      min_points, th1, th2, max_speed, max_iter, min_spread, centre_check,
                      out_idx, out_vx, out_vy, max_window_us=0, slow_px=2.0,
                      refit_failed=True, refractory_updates=True):
    """Process events in order, updating ``ts`` in place; returns the number of flow events.

    ``min_spread`` (px): the neighbours' positions must spread at least this much (standard
    deviation) across their principal direction, 0 = off (jAER). ``centre_check``: drop the
    estimate when the event itself lies farther than ``th2`` (s) from the final plane (the plane
    then describes other, older structure). ``out_idx`` (int64),
    ``out_vx``, ``out_vy`` (float64) need room for ``len(x)`` entries.

    Speed-adaptive window (on when ``max_window_us > window_us``; not for ``original``): when
    the fit with ``window_us`` says the edge moved less than ``slow_px`` px within the window
    (or, with ``refit_failed``, gives no estimate), refit with the window in which it would
    move ``slow_px`` px, W = slow_px |g|, at most ``max_window_us`` (the longest when there
    is no estimate); repeat while the window grows (at most :data:`MAX_REFITS` refits). A
    refit's centre check limit (and the iterative fits' residual limit) is ``th2 W / window_us``
    (the same fraction of the time per pixel). The last fit is the result; a failed refit gives
    no flow. Runs :func:`plane_flow_adaptive_kernel`.

    ``refractory_updates`` (jAER: true): an event within ``refractory_us`` still updates the
    surface; false: it is dropped entirely (the thesis's description), so the surface holds the
    onset of each pixel's burst and the refractory period counts from the last onset.
    """
    if max_window_us > window_us and variant != 3:
        return plane_flow_adaptive_kernel(x, y, t, p, ts, variant, r, window_us, refractory_us,
                                          margin, min_points, th1, th2, max_speed, max_iter,
                                          min_spread, centre_check, out_idx, out_vx, out_vy,
                                          max_window_us, slow_px, refit_failed,
                                          refractory_updates)
    return event_loop(x, y, t, p, ts, variant, r, window_us, refractory_us, margin, min_points,
                      th1, th2, max_speed, max_iter, min_spread, centre_check, out_idx, out_vx,
                      out_vy, max_window_us, slow_px, refit_failed, refractory_updates, False)
