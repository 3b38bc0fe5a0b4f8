"""Numba kernel of ``lk_flow``: event-based Lucas-Kanade (Benosman 2012, as in jAER).

One pass over a packet's events in time order. State (kept by the filter between packets):

* ``last`` int64 ``[2, H, W]``: per polarity (index 0 OFF, 1 ON) the newest timestamp of every
  pixel, :data:`EMPTY_T` where none; ``second`` the same for the timestamp before it (shape
  ``[2, 0, 0]`` when only one is kept); ``fifo`` int64 ``[2, H, W, depth - 2]`` the older ones,
  newest first, contiguous per pixel. Most neighbours are inactive and need only a read of
  ``last`` (contiguous in x); most active ones have one event in the window and need one read of
  ``second``; only the rest walk their ``fifo`` (one or two cache lines). An insert shifts the
  pixel's timestamps back and drops its oldest; a timestamp already outside the window when it
  would be shifted can never be counted again (events come in time order), nor can anything
  behind it, so the shift stops there: a walk stops at the first timestamp outside the window,
  and the slot it then reads still holds one that is older still;
* ``speed_state`` float64 ``[2]``: running mean of speeds and a flag "mean initialised".

Gradient codes: 0 backward, 1 central (first order), 2 central2 (second order, 5 points),
3 Savitzky-Golay (one linear plane fit per neighbourhood).

Two modes, see ``docs/explanation/lk_flow.md``:

* faithful: jAER's LucasKanadeFlow (2016): image N = count of events within the window, stencils
  on N, temporal term N x stencil normalisation x 20, eigenvalue test against ``eig_threshold``,
  normal flow from the centre pixel; border events do not touch the memory; speed control with a
  mean that starts at 0 and mixes every computed speed (zeros included).
* calibrated: image F = 1 - age / window of each pixel's oldest event within the window (the
  onset of its current activity), whose time derivative is exactly -1 / window while the pixel
  stays active; stencils only over pixels with events in the window (falling back to
  lower-order or one-sided differences); scale-free eigenvalue ratio test; normal flow as the
  least-squares solution along the dominant eigenvector; speed ceiling.
"""

from __future__ import annotations

import numpy as np
from numba import njit

EMPTY_T = -(1 << 62)

BACKWARD, CENTRAL, CENTRAL2, SAVITZKY_GOLAY = 0, 1, 2, 3


def new_state(height: int, width: int, depth: int):
    """Fresh state arrays (last, second, fifo, speed_state) for ``depth`` timestamps per pixel
    and polarity."""
    last = np.full((2, height, width), EMPTY_T, np.int64)
    second = np.full((2, height, width) if depth > 1 else (2, 0, 0), EMPTY_T, np.int64)
    fifo = np.full((2, height, width, max(depth - 2, 0)), EMPTY_T, np.int64)
    speed_state = np.zeros(2, np.float64)
    return last, second, fifo, speed_state


@njit(cache=True)
def _calibrated_fd(LI, LJ, n_act, F, V, gradient, w_inv, eig_ratio, tol, GX, GY, keep):
    """Calibrated finite-difference LK over pixels with events. Returns (vx, vy, ok).

    Per pixel and axis the variant's stencil when all its points have events, else the mean of
    the available one-sided differences (central variants) or the forward difference (backward
    variant); pixels without any usable difference give no equation. With ``tol > 0`` the
    equations whose slope disagrees with the first solution by more than ``tol`` (relative:
    |grad F . v W - 1| > tol) are dropped and the rest solved again, once.
    ``LI``, ``LJ``: the ``n_act`` active pixels of the neighbourhood (indices into ``F``, ``V``);
    ``GX``, ``GY``, ``keep``: scratch arrays of at least ``n_act`` entries."""
    m = 0
    for q in range(n_act):
        i = LI[q]
        j = LJ[q]
        fc = F[i, j]
        # x
        vm = V[i - 1, j]
        vp = V[i + 1, j]
        if gradient == BACKWARD:
            if vm > 0.0:
                gx = fc - F[i - 1, j]
            elif vp > 0.0:
                gx = F[i + 1, j] - fc
            else:
                continue
        else:
            den = vm + vp
            if den == 0.0:
                continue
            gx = (vp * (F[i + 1, j] - fc) + vm * (fc - F[i - 1, j])) / den
            if gradient == CENTRAL2 and den == 2.0 and V[i - 2, j] > 0.0 \
                    and V[i + 2, j] > 0.0:
                gx = (F[i - 2, j] - 8.0 * F[i - 1, j] + 8.0 * F[i + 1, j]
                      - F[i + 2, j]) / 12.0
        # y
        vm = V[i, j - 1]
        vp = V[i, j + 1]
        if gradient == BACKWARD:
            if vm > 0.0:
                gy = fc - F[i, j - 1]
            elif vp > 0.0:
                gy = F[i, j + 1] - fc
            else:
                continue
        else:
            den = vm + vp
            if den == 0.0:
                continue
            gy = (vp * (F[i, j + 1] - fc) + vm * (fc - F[i, j - 1])) / den
            if gradient == CENTRAL2 and den == 2.0 and V[i, j - 2] > 0.0 \
                    and V[i, j + 2] > 0.0:
                gy = (F[i, j - 2] - 8.0 * F[i, j - 1] + 8.0 * F[i, j + 1]
                      - F[i, j + 2]) / 12.0
        GX[m] = gx
        GY[m] = gy
        keep[m] = True
        m += 1
    if m < 2:
        return 0.0, 0.0, False
    vx, vy, ok = _solve_rows(GX, GY, keep, m, w_inv, eig_ratio)
    if not ok or tol <= 0.0:
        return vx, vy, ok
    dropped = 0
    for q in range(m):
        if abs((GX[q] * vx + GY[q] * vy) / w_inv - 1.0) > tol:
            keep[q] = False
            dropped += 1
    if dropped == 0:
        return vx, vy, ok
    if m - dropped < 2:
        return 0.0, 0.0, False
    return _solve_rows(GX, GY, keep, m, w_inv, eig_ratio)


@njit(cache=True)
def _solve_rows(GX, GY, keep, m, b, eig_ratio):
    """Least squares of rows (GX, GY) . v = b (kept rows): full solution when
    lambda2 >= eig_ratio lambda1, else along the dominant eigenvector. Returns (vx, vy, ok)."""
    sx2 = 0.0
    sy2 = 0.0
    sxy = 0.0
    sx = 0.0
    sy = 0.0
    for q in range(m):
        if keep[q]:
            gx = GX[q]
            gy = GY[q]
            sx2 += gx * gx
            sy2 += gy * gy
            sxy += gx * gy
            sx += gx
            sy += gy
    sxt = sx * b
    syt = sy * b
    pp = sx2 + sy2
    disc = np.sqrt((sx2 - sy2) * (sx2 - sy2) + 4.0 * sxy * sxy)
    lam1 = 0.5 * (pp + disc)
    lam2 = 0.5 * (pp - disc)
    if not lam1 > 0.0:
        return 0.0, 0.0, False
    if lam2 > 0.0 and lam2 >= eig_ratio * lam1:
        qq = sx2 * sy2 - sxy * sxy
        return (sy2 * sxt - sxy * syt) / qq, (sx2 * syt - sxy * sxt) / qq, True
    # least squares restricted to the dominant eigenvector: normal flow
    if sxy != 0.0:
        ex = lam1 - sy2
        ey = sxy
    elif sx2 >= sy2:
        ex = 1.0
        ey = 0.0
    else:
        ex = 0.0
        ey = 1.0
    en = np.sqrt(ex * ex + ey * ey)
    ex /= en
    ey /= en
    proj = (ex * sxt + ey * syt) / lam1
    return ex * proj, ey * proj, True


@njit(cache=True)
def _plane(U, W, FV, keep, m):
    """Least-squares plane F = c + gx u + gy w over the kept points. Returns (c, gx, gy, ok)."""
    s1 = 0.0
    su = 0.0
    sw = 0.0
    suu = 0.0
    sww = 0.0
    suw = 0.0
    sf = 0.0
    suf = 0.0
    swf = 0.0
    for q in range(m):
        if keep[q]:
            u = U[q]
            w = W[q]
            f = FV[q]
            s1 += 1.0
            su += u
            sw += w
            suu += u * u
            sww += w * w
            suw += u * w
            sf += f
            suf += u * f
            swf += w * f
    if s1 < 3.0:
        return 0.0, 0.0, 0.0, False
    cuu = suu - su * su / s1
    cww = sww - sw * sw / s1
    cuw = suw - su * sw / s1
    cuf = suf - su * sf / s1
    cwf = swf - sw * sf / s1
    det = cuu * cww - cuw * cuw
    if det <= 1e-9 * (cuu * cww + 1e-300):
        return 0.0, 0.0, 0.0, False  # collinear support: no plane
    gx = (cww * cuf - cuw * cwf) / det
    gy = (cuu * cwf - cuw * cuf) / det
    c = (sf - gx * su - gy * sw) / s1
    return c, gx, gy, True


@njit(cache=True)
def _calibrated_sg(U, W, FV, keep, m, w_inv, tol):
    """Calibrated Savitzky-Golay: least-squares plane of F over the ``m`` pixels with events
    (``U``, ``W``: coordinates centred on the event, ``FV``: F; listed by the gather, ``keep``
    all True); normal flow (1 / W) g / |g|^2. With ``tol > 0`` pixels farther than ``tol`` px
    (along the normal) from the plane are dropped and the plane fitted again, once."""
    c, gx, gy, ok = _plane(U, W, FV, keep, m)
    if not ok:
        return 0.0, 0.0, False
    g2 = gx * gx + gy * gy
    if not g2 > 0.0:
        return 0.0, 0.0, False
    if tol > 0.0:
        lim = tol * np.sqrt(g2)
        dropped = 0
        for q in range(m):
            if abs(FV[q] - c - gx * U[q] - gy * W[q]) > lim:
                keep[q] = False
                dropped += 1
        if dropped:
            c, gx, gy, ok = _plane(U, W, FV, keep, m)
            if not ok:
                return 0.0, 0.0, False
            g2 = gx * gx + gy * gy
            if not g2 > 0.0:
                return 0.0, 0.0, False
    return gx * w_inv / g2, gy * w_inv / g2, True


@njit(cache=True)
def _centre_offset_points(U, W, FV, m, vx, vy, w_inv):
    """How far (px, along the normal) the current event's onset lies from the plane that the
    flow v implies through the other active pixels of the (2r+1)^2 neighbourhood (the ``m``
    listed points ``U``, ``W``, ``FV``; the event is the one at (0, 0)): the slope is
    g = v / (W |v|^2), the offset the mean of F - g.u over those pixels. Large when the event
    belongs to a newer edge than the onsets around it. Infinite without other active pixels."""
    v2 = vx * vx + vy * vy
    if not v2 > 0.0:
        return np.inf
    gx = vx * w_inv / v2
    gy = vy * w_inv / v2
    sc = 0.0
    n = 0
    fc = 0.0
    for q in range(m):
        if U[q] == 0.0 and W[q] == 0.0:
            fc = FV[q]
        else:
            sc += FV[q] - gx * U[q] - gy * W[q]
            n += 1
    if n == 0:
        return np.inf
    return abs(fc - sc / n) / np.sqrt(gx * gx + gy * gy)


@njit(cache=True)
def _faithful(N, d, S, R, gradient, stencil_norm, sg_norm, thr):
    """jAER's LucasKanadeFlow on the count image N. Returns (vx, vy)."""
    gxs = 0.0
    gys = 0.0
    if gradient == SAVITZKY_GOLAY:
        for j in range(S):
            for i in range(S):
                gxs += (i - R) * N[i, j]
                gys += (j - R) * N[i, j]
        gxs /= sg_norm
        gys /= sg_norm
    sx2 = 0.0
    sy2 = 0.0
    sxy = 0.0
    sxt = 0.0
    syt = 0.0
    gxc = 0.0
    gyc = 0.0
    ntc = 0.0
    for j in range(d, S - d):
        for i in range(d, S - d):
            if gradient == BACKWARD:
                gx = float(N[i, j] - N[i - 1, j])
                # jAER's y points up: its backward step y - 1 is our y + 1
                gy = float(N[i, j + 1] - N[i, j])
            elif gradient == CENTRAL:
                gx = float(N[i + 1, j] - N[i - 1, j])
                gy = float(N[i, j + 1] - N[i, j - 1])
            elif gradient == CENTRAL2:
                gx = float(N[i - 2, j] - 8 * N[i - 1, j] + 8 * N[i + 1, j] - N[i + 2, j])
                gy = float(N[i, j - 2] - 8 * N[i, j - 1] + 8 * N[i, j + 1] - N[i, j + 2])
            else:
                gx = gxs
                gy = gys
            nt = N[i, j] * stencil_norm * 20.0
            sx2 += gx * gx
            sy2 += gy * gy
            sxy += gx * gy
            sxt += gx * nt
            syt += gy * nt
            if i == R and j == R:
                gxc = gx
                gyc = gy
                ntc = nt
    pp = sx2 + sy2
    disc = np.sqrt((sx2 - sy2) * (sx2 - sy2) + 4.0 * sxy * sxy)
    lam1 = 0.5 * (pp + disc)
    lam2 = 0.5 * (pp - disc)
    if lam1 < thr:
        return 0.0, 0.0
    if lam2 < thr:
        g2 = gxc * gxc + gyc * gyc
        if g2 > 0.0:
            return -gxc * ntc / g2, -gyc * ntc / g2
        return 0.0, 0.0
    qq = sx2 * sy2 - sxy * sxy
    return (sxy * syt - sy2 * sxt) / qq, (sxy * sxt - sx2 * syt) / qq


@njit(cache=True, inline="always")
def _gather_calibrated(last, second, fifo, k, xe, ye, te, tmin, w_inv, R, S, d, F, V, LI, LJ,
                       PU, PW, FV, keep):
    """Calibrated gather of the neighbourhood (incl. the stencil margin) of the event at
    (``xe``, ``ye``, ``te``), polarity ``k``, over the timestamps >= ``tmin``: ``F`` = 1 - age of
    the oldest such timestamp x ``w_inv``, ``V`` = 1 where the pixel has one, else both 0; lists
    the active pixels of the (2r+1)^2 neighbourhood in ``LI``, ``LJ``, ``PU``, ``PW``, ``FV``
    (``keep`` True). Returns their number."""
    has2 = second.shape[1] > 0
    deep = fifo.shape[3]
    m_list = 0
    for j in range(S):
        yy = ye - R + j
        jm = j < d or j >= S - d
        for i in range(S):
            if jm and (i < d or i >= S - d):
                continue  # corner of the stencil margin: never read
            xx = xe - R + i
            ts = last[k, yy, xx]
            if ts >= tmin:
                oldest = ts
                if has2:
                    ts = second[k, yy, xx]
                    if ts >= tmin:
                        oldest = ts
                        for jj in range(deep):
                            ts = fifo[k, yy, xx, jj]
                            if ts < tmin:
                                break
                            oldest = ts
                fv = 1.0 - (te - oldest) * w_inv
                F[i, j] = fv
                V[i, j] = 1.0
                if i >= d and i < S - d and not jm:
                    LI[m_list] = i
                    LJ[m_list] = j
                    PU[m_list] = float(i - R)
                    PW[m_list] = float(j - R)
                    FV[m_list] = fv
                    keep[m_list] = True
                    m_list += 1
            else:
                F[i, j] = 0.0
                V[i, j] = 0.0
    return m_list


@njit(cache=True, inline="always")
def _estimate_calibrated(last, second, fifo, k, xe, ye, te, window_us, w_inv, w_inv_s, R, S, d,
                         gradient, min_active, eig_ratio, refit_tolerance, centre_check_px,
                         max_speed_pxs, F, V, LI, LJ, PU, PW, FV, keep, GX, GY):
    """Calibrated flow of one event from the timestamps of age < ``window_us`` (``w_inv`` =
    1 / window_us, ``w_inv_s`` = 1e6 / window_us): gather, fit (Savitzky-Golay plane or finite
    differences), centre check, speed ceiling. Returns (vx, vy, ok); ok False when there is no
    usable estimate."""
    m_list = _gather_calibrated(last, second, fifo, k, xe, ye, te, te - (window_us - 1), w_inv,
                                R, S, d, F, V, LI, LJ, PU, PW, FV, keep)
    if m_list < min_active:
        return 0.0, 0.0, False
    if gradient == SAVITZKY_GOLAY:
        vx, vy, ok = _calibrated_sg(PU, PW, FV, keep, m_list, w_inv_s, refit_tolerance)
    else:
        vx, vy, ok = _calibrated_fd(LI, LJ, m_list, F, V, gradient, w_inv_s, eig_ratio,
                                    refit_tolerance, GX, GY, keep)
    if not ok:
        return 0.0, 0.0, False
    if centre_check_px > 0.0 and _centre_offset_points(
            PU, PW, FV, m_list, vx, vy, w_inv_s) > centre_check_px:
        return 0.0, 0.0, False
    v = np.sqrt(vx * vx + vy * vy)
    if not np.isfinite(v) or v == 0.0 or v > max_speed_pxs:
        return 0.0, 0.0, False
    return vx, vy, True


@njit(cache=True)
def _reestimate(last, second, fifo, k, xe, ye, te, window_us, R, S, d, gradient, min_active,
                eig_ratio, refit_tolerance, centre_check_px, max_speed_pxs, F, V, LI, LJ, PU, PW,
                FV, keep, GX, GY):
    """:func:`_estimate_calibrated` with another window (not inlined: the main loop keeps one
    copy of the estimate, for speed)."""
    return _estimate_calibrated(last, second, fifo, k, xe, ye, te, window_us, 1.0 / window_us,
                                1e6 / window_us, R, S, d, gradient, min_active, eig_ratio,
                                refit_tolerance, centre_check_px, max_speed_pxs, F, V, LI, LJ,
                                PU, PW, FV, keep, GX, GY)


#: calibrated speed-adaptive window: estimates per event at most (the first with ``window_us``)
MAX_PASSES = 3


@njit(cache=True)
def lk_flow_run(x, y, t, p, last, second, fifo, speed_state, r, window_us, refractory_us, gradient,
                faithful, eig_threshold, eig_ratio, speed_control, mix, max_factor,
                max_speed_pxs, refit_tolerance, centre_check_px, max_window_us, slow_px,
                out_idx, out_vx, out_vy):
    """Process events in order; write flow of emitted events into ``out_*``; return their count.

    ``out_*`` must have room for ``len(t)`` entries. ``max_window_us`` > ``window_us``
    (calibrated mode only; else ignored) turns on the speed-adaptive window: an event whose
    estimate with ``window_us`` fails, or says that the edge crosses fewer than ``slow_px`` px
    within the window, is estimated again with the window the estimate asks for,
    min(``max_window_us``, ``slow_px`` / speed) (``max_window_us`` after a failure), at most
    :data:`MAX_PASSES` estimates in all; an estimate from a longer window is kept only if it is
    slow enough to need it (the edge crosses fewer than ``slow_px`` px within the previous
    window), and the last such estimate is the event's flow.
    """
    _, height, width = last.shape
    has2 = second.shape[1] > 0
    deep = fifo.shape[3]
    d = 1
    if gradient == CENTRAL2:
        d = 2
    elif gradient == SAVITZKY_GOLAY:
        d = 0
    R = r + d
    S = 2 * R + 1
    N = np.zeros((S, S), np.int64)
    F = np.zeros((S, S), np.float64)
    V = np.zeros((S, S), np.float64)
    GX = np.zeros(S * S, np.float64)
    GY = np.zeros(S * S, np.float64)
    FV = np.zeros(S * S, np.float64)
    keep = np.zeros(S * S, np.bool_)
    w_inv = 1.0 / window_us
    w_inv_s = 1e6 / window_us
    adaptive = not faithful and max_window_us > window_us
    if faithful:
        wlim = window_us          # jAER keeps timestamps with age <= window
    elif adaptive:
        wlim = max_window_us - 1  # the memory must hold the longest window
    else:
        wlim = window_us - 1      # calibrated: age < window (weight > 0)
    slow_us = slow_px * 1e6       # px µs/s: speed x window below which the edge is too slow
    # Savitzky-Golay (faithful): sum of i^2 over the full (2r+1)^2 window
    sg_norm = (2 * r + 1) * r * (r + 1) * (2 * r + 1) / 3.0
    stencil_norm = 1.0
    if gradient == CENTRAL:
        stencil_norm = 2.0
    elif gradient == CENTRAL2:
        stencil_norm = 12.0
    elif gradient == SAVITZKY_GOLAY:
        stencil_norm = 1.0 / r
    # calibrated: fewest active pixels of the (2r+1)^2 neighbourhood that can give flow (two
    # equations, three points for a plane; the centre check needs a neighbour besides the event)
    min_active = 3 if gradient == SAVITZKY_GOLAY else 2
    # calibrated: the gather lists the active pixels of the neighbourhood (in the order the
    # fits and the centre check visit them, so their sums are unchanged); faithful: counts N
    LI = np.zeros(S * S, np.int64)
    LJ = np.zeros(S * S, np.int64)
    PU = np.zeros(S * S, np.float64)
    PW = np.zeros(S * S, np.float64)
    n_out = 0
    for e in range(len(t)):
        xe = np.int64(x[e])
        ye = np.int64(y[e])
        te = t[e]
        k = 1 if p[e] > 0 else 0
        inside = xe >= R and xe < width - R and ye >= R and ye < height - R
        if faithful and not inside:
            continue  # jAER: border events never reach the memory
        prev = last[k, ye, xe]
        if has2 and prev >= te - wlim:  # prev can still be counted: shift it back
            p2 = second[k, ye, xe]
            if deep > 0 and p2 >= te - wlim:
                for j in range(deep - 1, 0, -1):
                    fifo[k, ye, xe, j] = fifo[k, ye, xe, j - 1]
                fifo[k, ye, xe, 0] = p2
            second[k, ye, xe] = prev
        last[k, ye, xe] = te
        if not inside:
            continue
        if te - prev < refractory_us:
            continue
        if faithful:
            # counts of the neighbourhood incl. the stencil margin
            tmin = te - wlim
            for j in range(S):
                yy = ye - R + j
                jm = j < d or j >= S - d
                for i in range(S):
                    if jm and (i < d or i >= S - d):
                        continue  # corner of the stencil margin: never read
                    xx = xe - R + i
                    ts = last[k, yy, xx]
                    n = 0
                    if ts >= tmin:
                        n = 1
                        if has2:
                            ts = second[k, yy, xx]
                            if ts >= tmin:
                                n = 2
                                for jj in range(deep):
                                    if fifo[k, yy, xx, jj] < tmin:
                                        break
                                    n += 1
                    N[i, j] = n
            vx, vy = _faithful(N, d, S, R, gradient, stencil_norm, sg_norm, eig_threshold)
            v = np.sqrt(vx * vx + vy * vy)
            if speed_control:
                speed_state[0] = (1.0 - mix) * speed_state[0] + mix * v
                if v > speed_state[0] * max_factor:
                    continue
            if v == 0.0 or not np.isfinite(v):
                continue
        else:
            vx, vy, ok = _estimate_calibrated(
                last, second, fifo, k, xe, ye, te, window_us, w_inv, w_inv_s, R, S, d,
                gradient, min_active,
                eig_ratio, refit_tolerance, centre_check_px, max_speed_pxs, F, V, LI, LJ, PU,
                PW, FV, keep, GX, GY)
            if adaptive:
                win = window_us
                for _ in range(MAX_PASSES - 1):
                    if ok:
                        v = np.sqrt(vx * vx + vy * vy)
                        if v * win >= slow_us:
                            break  # the edge crosses slow_px within the window: resolved
                        want = slow_us / v
                        nxt = max_window_us if want >= max_window_us else np.int64(
                            np.ceil(want))
                    else:
                        nxt = max_window_us
                    if nxt <= win:
                        break
                    wx, wy, wok = _reestimate(
                        last, second, fifo, k, xe, ye, te, nxt, R, S, d, gradient, min_active,
                        eig_ratio, refit_tolerance, centre_check_px, max_speed_pxs, F, V, LI,
                        LJ, PU, PW, FV, keep, GX, GY)
                    # kept only if slow enough to need the longer window
                    if not wok or np.sqrt(wx * wx + wy * wy) * win >= slow_us:
                        break
                    vx = wx
                    vy = wy
                    ok = True
                    win = nxt
            if not ok:
                continue
            if speed_control:
                v = np.sqrt(vx * vx + vy * vy)
                if speed_state[1] == 0.0:
                    speed_state[0] = v
                    speed_state[1] = 1.0
                else:
                    speed_state[0] = (1.0 - mix) * speed_state[0] + mix * v
                if v > speed_state[0] * max_factor:
                    continue
        out_idx[n_out] = e
        out_vx[n_out] = vx
        out_vy[n_out] = vy
        n_out += 1
    return n_out
