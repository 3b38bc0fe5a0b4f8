"""Numba kernel of ``lk_flow``: event-based Lucas-Kanade (Benosman 2012, as in jAER).

One pass over a packet's events in time order (:func:`lk_flow_run`, constants in
:class:`LKParams`). State (:class:`LKState`, kept by the filter between packets):

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
* ``speed`` float64 ``[2]``: running mean of speeds and a flag "mean initialised"
  (:data:`MEAN_SPEED`, :data:`MEAN_STARTED`).

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

from typing import NamedTuple

import numpy as np
from numba import njit

from evchain.kernels.fit import plane_fit_raw, sym2_det, sym2_eigenvalues, sym2_solve

EMPTY_T = -(1 << 62)

BACKWARD, CENTRAL, CENTRAL2, SAVITZKY_GOLAY = 0, 1, 2, 3

#: entries of ``LKState.speed``: the running mean speed, and 1 once it is initialised
MEAN_SPEED, MEAN_STARTED = 0, 1

#: calibrated speed-adaptive window: estimates per event at most (the first with ``window_us``)
MAX_PASSES = 3


class LKParams(NamedTuple):
    """Constants of :func:`lk_flow_run`; build with :func:`evchain.kernels.records.record`."""

    r: int                   #: half-width of the (2r+1)^2 neighbourhood, px
    window_us: int           #: age of the timestamps counted, µs
    refractory_us: int       #: no flow this soon after the pixel's previous event, µs
    gradient: int            #: BACKWARD, CENTRAL, CENTRAL2 or SAVITZKY_GOLAY
    faithful: bool           #: jAER's LucasKanadeFlow (else calibrated)
    eig_threshold: float     #: faithful: eigenvalue threshold
    eig_ratio: float         #: calibrated: full flow when lambda2 >= eig_ratio lambda1
    speed_control: bool      #: drop events faster than max_factor x the running mean speed
    mix: float               #: mixing factor of the running mean speed
    max_factor: float        #: speed control's factor
    max_speed_pxs: float     #: calibrated: speed ceiling, px/s
    refit_tolerance: float   #: calibrated: refit tolerance (0: off)
    centre_check_px: float   #: calibrated: centre check limit, px (0: off)
    max_window_us: int       #: calibrated: speed-adaptive window up to this, µs (off unless >
    #: window_us)
    slow_px: float           #: adaptive window: distance an edge must cross within it, px
    min_window_us: int       #: calibrated: short window tried first, µs (off unless 0 < it <
    #: window_us)
    fast_px: float           #: short window: its estimate stands when the edge crosses at least
    #: this within it, px


class LKState(NamedTuple):
    """The memory of :func:`lk_flow_run` (see the module docstring), from :func:`new_state`."""

    last: np.ndarray    #: int64 [2, H, W]: newest timestamp per polarity and pixel, µs
    second: np.ndarray  #: int64 [2, H, W] (or [2, 0, 0]): the one before it
    fifo: np.ndarray    #: int64 [2, H, W, depth - 2]: the older ones, newest first
    speed: np.ndarray   #: float64 [2]: running mean speed; 1 once initialised


def new_state(height: int, width: int, depth: int) -> LKState:
    """Fresh memory for ``depth`` timestamps per pixel and polarity (all :data:`EMPTY_T`) and a
    running mean speed not yet started."""
    last = np.full((2, height, width), EMPTY_T, np.int64)
    second = np.full((2, height, width) if depth > 1 else (2, 0, 0), EMPTY_T, np.int64)
    fifo = np.full((2, height, width, max(depth - 2, 0)), EMPTY_T, np.int64)
    speed = np.zeros(2, np.float64)
    return LKState(last, second, fifo, speed)


# -- calibrated mode: fits ---------------------------------------------------------------------


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


@njit(cache=True, inline="always")
def _dominant_direction(sx2, sy2, sxy, lam1):
    """Unit eigenvector of the structure tensor [[sx2, sxy], [sxy, sy2]] for its larger
    eigenvalue ``lam1``."""
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
    return ex / en, ey / en


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
    lam1, lam2 = sym2_eigenvalues(sx2, sxy, sy2)
    if not lam1 > 0.0:
        return 0.0, 0.0, False
    if lam2 > 0.0 and lam2 >= eig_ratio * lam1:
        vx, vy = sym2_solve(sx2, sxy, sy2, sxt, syt, sym2_det(sx2, sxy, sy2))
        return vx, vy, True
    # least squares restricted to the dominant eigenvector: normal flow
    ex, ey = _dominant_direction(sx2, sy2, sxy, lam1)
    proj = (ex * sxt + ey * syt) / lam1
    return ex * proj, ey * proj, True


@njit(cache=True, inline="always")
def _calibrated_sg(U, W, FV, keep, m, w_inv, tol):
    """Calibrated Savitzky-Golay: least-squares plane of F over the ``m`` pixels with events
    (``U``, ``W``: coordinates centred on the event, ``FV``: F; listed by the gather, ``keep``
    all True); normal flow (1 / W) g / |g|^2. With ``tol > 0`` pixels farther than ``tol`` px
    (along the normal) from the plane are dropped and the plane fitted again, once."""
    c, gx, gy, ok = plane_fit_raw(U, W, FV, keep, m)
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
            c, gx, gy, ok = plane_fit_raw(U, W, FV, keep, m)
            if not ok:
                return 0.0, 0.0, False
            g2 = gx * gx + gy * gy
            if not g2 > 0.0:
                return 0.0, 0.0, False
    return gx * w_inv / g2, gy * w_inv / g2, True


@njit(cache=True, inline="always")
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


# -- faithful mode -----------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _count_slopes(N, S, R, sg_norm):
    """jAER's Savitzky-Golay gradient: one slope pair for the whole window."""
    gxs = 0.0
    gys = 0.0
    for j in range(S):
        for i in range(S):
            gxs += (i - R) * N[i, j]
            gys += (j - R) * N[i, j]
    return gxs / sg_norm, gys / sg_norm


@njit(cache=True)
def _faithful(N, d, S, R, gradient, stencil_norm, sg_norm, thr):
    """jAER's LucasKanadeFlow on the count image N. Returns (vx, vy)."""
    gxs = 0.0
    gys = 0.0
    if gradient == SAVITZKY_GOLAY:
        gxs, gys = _count_slopes(N, S, R, sg_norm)
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
    lam1, lam2 = sym2_eigenvalues(sx2, sxy, sy2)
    if lam1 < thr:
        return 0.0, 0.0
    if lam2 < thr:
        g2 = gxc * gxc + gyc * gyc
        if g2 > 0.0:
            return -gxc * ntc / g2, -gyc * ntc / g2
        return 0.0, 0.0
    # jAER's sign: the solution of S v = -(sxt, syt)
    return sym2_solve(sx2, sxy, sy2, -sxt, -syt, sym2_det(sx2, sxy, sy2))


# -- the memory --------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _gather_counts(last, second, fifo, k, xe, ye, tmin, R, S, d, N):
    """Faithful gather: ``N`` = the counts of timestamps >= ``tmin`` over the neighbourhood of
    (xe, ye) including the stencil margin ``d`` (its corners are never read)."""
    has2 = second.shape[1] > 0
    deep = fifo.shape[3]
    for j in range(S):
        yy = ye - R + j
        jm = j < d or j >= S - d
        for i in range(S):
            if jm and (i < d or i >= S - d):
                continue  # corner of the stencil margin: never read
            xx = xe - R + i
            n = 0
            if last[k, yy, xx] >= tmin:
                n = 1
            if n == 1 and has2 and second[k, yy, xx] >= tmin:
                n = 2
                for jj in range(deep):
                    if fifo[k, yy, xx, jj] < tmin:
                        break
                    n += 1
            N[i, j] = n


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
            oldest = last[k, yy, xx]
            if oldest < tmin:
                if d:
                    F[i, j] = 0.0
                    V[i, j] = 0.0
                continue
            if has2 and second[k, yy, xx] >= tmin:
                oldest = second[k, yy, xx]
                for jj in range(deep):
                    ts = fifo[k, yy, xx, jj]
                    if ts < tmin:
                        break
                    oldest = ts
            fv = 1.0 - (te - oldest) * w_inv
            if d:
                F[i, j] = fv
                V[i, j] = 1.0
            if i >= d and i < S - d and not jm:
                if d:
                    LI[m_list] = i
                    LJ[m_list] = j
                PU[m_list] = float(i - R)
                PW[m_list] = float(j - R)
                FV[m_list] = fv
                keep[m_list] = True
                m_list += 1
    return m_list


# -- one event ---------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _estimate_calibrated(last, second, fifo, k, xe, ye, te, window_us, w_inv, w_inv_s, R, S, d,
                         min_active, prm, F, V, LI, LJ, PU, PW, FV, keep, GX, GY):
    """Calibrated flow of one event from the timestamps of age < ``window_us`` (``w_inv`` =
    1 / window_us, ``w_inv_s`` = 1e6 / window_us): gather, fit (Savitzky-Golay plane or finite
    differences), centre check, speed ceiling. Returns (vx, vy, ok); ok False when there is no
    usable estimate. ``F`` .. ``GY``: the scratch arrays of :func:`_lk_events`."""
    m_list = _gather_calibrated(last, second, fifo, k, xe, ye, te, te - (window_us - 1), w_inv,
                                R, S, d, F, V, LI, LJ, PU, PW, FV, keep)
    if m_list < min_active:
        return 0.0, 0.0, False
    if prm.gradient == SAVITZKY_GOLAY:
        vx, vy, ok = _calibrated_sg(PU, PW, FV, keep, m_list, w_inv_s, prm.refit_tolerance)
    else:
        vx, vy, ok = _calibrated_fd(LI, LJ, m_list, F, V, prm.gradient, w_inv_s, prm.eig_ratio,
                                    prm.refit_tolerance, GX, GY, keep)
    if not ok:
        return 0.0, 0.0, False
    if prm.centre_check_px > 0.0 and _centre_offset_points(
            PU, PW, FV, m_list, vx, vy, w_inv_s) > prm.centre_check_px:
        return 0.0, 0.0, False
    v = np.sqrt(vx * vx + vy * vy)
    if not np.isfinite(v) or v == 0.0 or v > prm.max_speed_pxs:
        return 0.0, 0.0, False
    return vx, vy, True


@njit(cache=True, inline="always")
def _next_window(ok, vx, vy, win, slow_us, max_window_us):
    """Adaptive window: the window (µs) the estimate (vx, vy) from window ``win`` asks for,
    min(max_window_us, slow_px / speed) (``max_window_us`` when not ``ok``); ``win`` itself
    when the edge crosses slow_px within ``win`` (``slow_us`` = slow_px x 1e6)."""
    if not ok:
        return max_window_us
    v = np.sqrt(vx * vx + vy * vy)
    if v * win >= slow_us:
        return win  # the edge crosses slow_px within the window: resolved
    want = slow_us / v
    return max_window_us if want >= max_window_us else np.int64(np.ceil(want))


@njit(cache=True, inline="always")
def _reestimate(last, second, fifo, k, xe, ye, te, window_us, R, S, d, min_active, prm, F, V,
                LI, LJ, PU, PW, FV, keep, GX, GY):
    """:func:`_estimate_calibrated` with another window (inlined, as are the fits it calls: a
    call with the scratch arrays as arguments costs more than the copies of the code)."""
    return _estimate_calibrated(last, second, fifo, k, xe, ye, te, window_us, 1.0 / window_us,
                                1e6 / window_us, R, S, d, min_active, prm, F, V, LI, LJ, PU, PW,
                                FV, keep, GX, GY)


@njit(cache=True, inline="always")
def _faithful_speed(mean, vx, vy, prm):
    """jAER's speed control: the running mean speed (from 0, mixing every computed speed) and
    whether the flow is kept: not faster than ``max_factor`` x the mean, not zero, finite."""
    v = np.sqrt(vx * vx + vy * vy)
    ok = True
    if prm.speed_control:
        mean = (1.0 - prm.mix) * mean + prm.mix * v
        ok = not v > mean * prm.max_factor
    return mean, ok and not (v == 0.0 or not np.isfinite(v))


@njit(cache=True, inline="always")
def _calibrated_speed(mean, started, vx, vy, prm):
    """Calibrated speed control: the running mean speed starts at the first speed; returns
    (mean, started, kept)."""
    if not prm.speed_control:
        return mean, started, True
    v = np.sqrt(vx * vx + vy * vy)
    if started == 0.0:
        mean = v
        started = 1.0
    else:
        mean = (1.0 - prm.mix) * mean + prm.mix * v
    return mean, started, not v > mean * prm.max_factor


@njit(cache=True, inline="always")
def _memory_window(prm, adaptive):
    """The oldest age (µs) the memory must keep countable."""
    if prm.faithful:
        return prm.window_us          # jAER keeps timestamps with age <= window
    if adaptive:
        return prm.max_window_us - 1  # the memory must hold the longest window
    return prm.window_us - 1          # calibrated: age < window (weight > 0)


@njit(cache=True, inline="always")
def _stencil(gradient, r):
    """(d, R, S): the stencil margin, the half-width R = r + d of the window read and its side
    S = 2 R + 1."""
    d = 1
    if gradient == CENTRAL2:
        d = 2
    elif gradient == SAVITZKY_GOLAY:
        d = 0
    return d, r + d, 2 * (r + d) + 1


@njit(cache=True, inline="always")
def _stencil_norm(gradient, r):
    """Faithful mode: the normalisation of the temporal term per gradient (jAER)."""
    if gradient == CENTRAL:
        return 2.0
    if gradient == CENTRAL2:
        return 12.0
    if gradient == SAVITZKY_GOLAY:
        return 1.0 / r
    return 1.0


@njit(cache=True, nogil=True)
def lk_flow_run(x, y, t, p, state, prm, out_idx, out_vx, out_vy):
    """Process events in order; write the flow of the emitted events into ``out_*``.

    ``prm.max_window_us`` > ``prm.window_us`` (calibrated mode only; else ignored) turns on the
    speed-adaptive window: an event whose estimate with ``window_us`` fails, or says that the
    edge crosses fewer than ``slow_px`` px within the window, is estimated again with the window
    the estimate asks for, min(``max_window_us``, ``slow_px`` / speed) (``max_window_us`` after a
    failure), at most :data:`MAX_PASSES` estimates in all; an estimate from a longer window is
    kept only if it is slow enough to need it (the edge crosses fewer than ``slow_px`` px within
    the previous window), and the last such estimate is the event's flow.

    0 < ``prm.min_window_us`` < ``prm.window_us`` (calibrated mode only) adds a shorter time
    scale: each event is first estimated with ``min_window_us``; when that succeeds and the
    edge crosses at least ``fast_px`` px within it, it is the event's flow (no further
    estimates), else the event is estimated as above.

    Parameters
    ----------
    x, y : uint16 ndarray, shape (n,)
        Pixel coordinates of the events, in time order.
    t : int64 ndarray, shape (n,)
        Timestamps, µs, non-decreasing (also across calls).
    p : int8 ndarray, shape (n,)
        Polarities (> 0: ON).
    state : LKState
        The memory (:func:`new_state`), updated in place.
    prm : LKParams
        The constants.
    out_idx : int64 ndarray, shape (>= n,)
        Out: indices of the emitted events.
    out_vx, out_vy : float64 ndarray, shape (>= n,)
        Out: their flow (calibrated: px/s; faithful: jAER's uncalibrated units).

    Returns
    -------
    int
        The number of emitted events (the filled length of ``out_*``).
    """
    S = _stencil(prm.gradient, prm.r)[2]
    n = S * S  # scratch: see _lk_events
    return _lk_events(x, y, t, p, state, prm, out_idx, out_vx, out_vy,
                      np.zeros((S, S), np.int64), np.zeros((S, S)), np.zeros((S, S)),
                      np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n, np.bool_),
                      np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n), np.zeros(n))


@njit(cache=True, _nrt=False)
def _lk_events(x, y, t, p, state, prm, out_idx, out_vx, out_vy, N, F, V, GX, GY, FV, keep, LI,
               LJ, PU, PW):
    """:func:`lk_flow_run` with its scratch arrays given: faithful counts N; calibrated onset
    image F and its validity V; the fits' finite differences GX, GY; the active pixels' F there
    FV, kept rows ``keep``, indices LI, LJ and offsets PU, PW.

    Compiled without reference counting: numba counts a reference for every array passed to or
    bound in the inlined helpers, per event, atomic operations that its pruning pass keeps where
    they straddle branches (docs/explanation/lk_flow.md, "Memory layout and speed"). It
    allocates nothing."""
    last, second, fifo, speed = state
    height = last.shape[1]
    width = last.shape[2]
    has2 = second.shape[1] > 0
    deep = fifo.shape[3]
    gradient = prm.gradient
    d, R, S = _stencil(gradient, prm.r)
    adaptive = not prm.faithful and prm.max_window_us > prm.window_us
    extra_passes = MAX_PASSES - 1 if adaptive else 0
    wlim = _memory_window(prm, adaptive)
    w_inv = 1.0 / prm.window_us
    w_inv_s = 1e6 / prm.window_us
    slow_us = prm.slow_px * 1e6  # px µs/s: speed x window below which the edge is too slow
    shorten = not prm.faithful and 0 < prm.min_window_us < prm.window_us
    fast_us = prm.fast_px * 1e6  # px µs/s: speed x short window from which its estimate stands
    r = prm.r
    # Savitzky-Golay (faithful): sum of i^2 over the full (2r+1)^2 window
    sg_norm = (2 * r + 1) * r * (r + 1) * (2 * r + 1) / 3.0
    stencil_norm = _stencil_norm(gradient, r)
    # calibrated: fewest active pixels of the (2r+1)^2 neighbourhood that can give flow (two
    # equations, three points for a plane; the centre check needs a neighbour besides the event)
    min_active = 3 if gradient == SAVITZKY_GOLAY else 2
    mean = speed[MEAN_SPEED]
    started = speed[MEAN_STARTED]
    n_out = 0
    for e in range(len(t)):
        xe = np.int64(x[e])
        ye = np.int64(y[e])
        te = t[e]
        k = 1 if p[e] > 0 else 0
        inside = xe >= R and xe < width - R and ye >= R and ye < height - R
        if prm.faithful and not inside:
            continue  # jAER: border events never reach the memory
        # into the memory: the older timestamps shift back only while they can still be
        # counted (age <= wlim); anything behind one outside the window never counts again
        prev = last[k, ye, xe]
        if has2 and prev >= te - wlim:  # prev can still be counted: shift it back
            p2 = second[k, ye, xe]
            if deep > 0 and p2 >= te - wlim:
                for j in range(deep - 1, 0, -1):
                    fifo[k, ye, xe, j] = fifo[k, ye, xe, j - 1]
                fifo[k, ye, xe, 0] = p2
            second[k, ye, xe] = prev
        last[k, ye, xe] = te
        if not inside or te - prev < prm.refractory_us:
            continue
        if prm.faithful:
            _gather_counts(last, second, fifo, k, xe, ye, te - wlim, R, S, d, N)
            vx, vy = _faithful(N, d, S, R, gradient, stencil_norm, sg_norm, prm.eig_threshold)
            mean, ok = _faithful_speed(mean, vx, vy, prm)
        else:
            # two time scales: first the short window, whose estimate stands for an edge fast
            # enough to cross fast_px within it (onsets of older edges that crossed the pixels
            # within window_us then stay out of the fit)
            fast = False
            if shorten:
                vx, vy, ok = _reestimate(last, second, fifo, k, xe, ye, te,
                                         np.int64(prm.min_window_us), R, S, d, min_active, prm,
                                         F, V, LI, LJ, PU, PW, FV, keep, GX, GY)
                fast = ok and np.sqrt(vx * vx + vy * vy) * prm.min_window_us >= fast_us
            if not fast:
                vx, vy, ok = _estimate_calibrated(last, second, fifo, k, xe, ye, te,
                                                  prm.window_us, w_inv, w_inv_s, R, S, d,
                                                  min_active, prm, F, V, LI, LJ, PU, PW, FV,
                                                  keep, GX, GY)
            # speed-adaptive window: again with the window the estimate asks for; a longer
            # window's estimate is kept only if it is slow enough to need it
            win = prm.window_us
            for _ in range(0 if fast else extra_passes):
                nxt = _next_window(ok, vx, vy, win, slow_us, prm.max_window_us)
                if nxt <= win:
                    break
                wx, wy, wok = _reestimate(last, second, fifo, k, xe, ye, te, nxt, R, S, d,
                                          min_active, prm, F, V, LI, LJ, PU, PW, FV, keep, GX,
                                          GY)
                if not wok or np.sqrt(wx * wx + wy * wy) * win >= slow_us:
                    break
                vx, vy, ok, win = wx, wy, True, nxt
            if ok:
                mean, started, ok = _calibrated_speed(mean, started, vx, vy, prm)
        if ok:
            out_idx[n_out] = e
            out_vx[n_out] = vx
            out_vy[n_out] = vy
            n_out += 1
    speed[MEAN_SPEED] = mean
    speed[MEAN_STARTED] = started
    return n_out
