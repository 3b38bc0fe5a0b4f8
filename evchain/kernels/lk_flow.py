"""Numba kernel of ``lk_flow``: event-based Lucas-Kanade (Benosman 2012, as in jAER).

One pass over a packet's events in time order. State (kept by the filter between packets):

* ``ring`` int64 ``[H, W, 2, depth]``: per pixel and polarity (index 0 OFF, 1 ON) the last
  ``depth`` timestamps, oldest overwritten first; empty slots hold :data:`EMPTY_T`;
* ``head`` int32 ``[H, W, 2]``: next write slot of each ring;
* ``speed_state`` float64 ``[2]``: running mean of speeds and a flag "mean initialised".

Gradient codes: 0 backward, 1 central (first order), 2 central2 (second order, 5 points),
3 Savitzky-Golay (one linear plane fit per neighbourhood).

Two modes, see ``docs/explanation/lk_flow.md``:

* faithful: jAER's LucasKanadeFlow (2016): image N = count of events within the window, stencils
  on N, temporal term N x stencil normalisation x 20, eigenvalue test against ``eig_threshold``,
  normal flow from the centre pixel; border events do not touch the memory; speed control with a
  mean that starts at 0 and mixes every computed speed (zeros included).
* calibrated: image F = sum over the window of (1 - age / window) per event, whose time
  derivative is -N / window (events per second); stencils only over pixels with events in the
  window (falling back to lower-order or one-sided differences); scale-free eigenvalue ratio test;
  normal flow as the least-squares solution along the dominant eigenvector; speed ceiling.
"""

from __future__ import annotations

import numpy as np
from numba import njit

EMPTY_T = -(1 << 62)

BACKWARD, CENTRAL, CENTRAL2, SAVITZKY_GOLAY = 0, 1, 2, 3


def stencil_margin(gradient: int) -> int:
    """Extra border (beyond the search distance) the gradient stencil reads."""
    return (1, 1, 2, 0)[gradient]


def new_state(height: int, width: int, depth: int):
    """Fresh state arrays (ring, head, speed_state)."""
    ring = np.full((height, width, 2, depth), EMPTY_T, np.int64)
    head = np.zeros((height, width, 2), np.int32)
    speed_state = np.zeros(2, np.float64)
    return ring, head, speed_state


@njit(cache=True, inline="always")
def _count(ring, head, yy, xx, k, t, wlim, w_inv, depth):
    """Events of one pixel and polarity with age <= wlim, and their weight sum 1 - age/W."""
    h = head[yy, xx, k]
    n = 0
    f = 0.0
    for j in range(depth):
        idx = h - 1 - j
        if idx < 0:
            idx += depth
        tau = t - ring[yy, xx, k, idx]
        if tau > wlim:
            break
        n += 1
        f += 1.0 - tau * w_inv
    return n, f


@njit(cache=True, inline="always")
def _deriv(F, N, i, j, di, dj, gradient):
    """Calibrated derivative of F at local (i, j) along (di, dj), preferring the variant's
    stencil and falling back to lower-order / one-sided differences over pixels with events.
    Returns (value, ok)."""
    c = N[i, j] > 0
    if not c:
        return 0.0, False
    pm = N[i - di, j - dj] > 0
    pp = N[i + di, j + dj] > 0
    if gradient == CENTRAL2 and pm and pp:
        if N[i - 2 * di, j - 2 * dj] > 0 and N[i + 2 * di, j + 2 * dj] > 0:
            return (F[i - 2 * di, j - 2 * dj] - 8.0 * F[i - di, j - dj]
                    + 8.0 * F[i + di, j + dj] - F[i + 2 * di, j + 2 * dj]) / 12.0, True
    if gradient == BACKWARD:
        if pm:
            return F[i, j] - F[i - di, j - dj], True
        if pp:
            return F[i + di, j + dj] - F[i, j], True
        return 0.0, False
    if pm and pp:
        return 0.5 * (F[i + di, j + dj] - F[i - di, j - dj]), True
    if pm:
        return F[i, j] - F[i - di, j - dj], True
    if pp:
        return F[i + di, j + dj] - F[i, j], True
    return 0.0, False


@njit(cache=True)
def lk_flow_run(x, y, t, p, ring, head, speed_state, r, window_us, refractory_us, gradient,
                faithful, eig_threshold, eig_ratio, speed_control, mix, max_factor,
                max_speed_pxs, out_idx, out_vx, out_vy):
    """Process events in order; write flow of emitted events into ``out_*``; return their count.

    ``out_*`` must have room for ``len(t)`` entries.
    """
    height, width, _, depth = ring.shape
    d = 1
    if gradient == CENTRAL2:
        d = 2
    elif gradient == SAVITZKY_GOLAY:
        d = 0
    R = r + d
    S = 2 * R + 1
    N = np.zeros((S, S), np.int64)
    F = np.zeros((S, S), np.float64)
    w_inv = 1.0 / window_us
    if faithful:
        wlim = window_us          # jAER keeps timestamps with age <= window
    else:
        wlim = window_us - 1      # calibrated: age < window (weight > 0)
    # Savitzky-Golay (faithful): sum of i^2 over the full (2r+1)^2 window
    sg_norm = (2 * r + 1) * r * (r + 1) * (2 * r + 1) / 3.0
    stencil_norm = 1.0
    if gradient == CENTRAL:
        stencil_norm = 2.0
    elif gradient == CENTRAL2:
        stencil_norm = 12.0
    elif gradient == SAVITZKY_GOLAY:
        stencil_norm = 1.0 / r
    n_out = 0
    for e in range(len(t)):
        xe = np.int64(x[e])
        ye = np.int64(y[e])
        te = t[e]
        k = 1 if p[e] > 0 else 0
        inside = xe >= R and xe < width - R and ye >= R and ye < height - R
        if faithful and not inside:
            continue  # jAER: border events never reach the memory
        h = head[ye, xe, k]
        prev = ring[ye, xe, k, h - 1 if h > 0 else depth - 1]
        ring[ye, xe, k, h] = te
        h += 1
        if h == depth:
            h = 0
        head[ye, xe, k] = h
        if not inside:
            continue
        if te - prev < refractory_us:
            continue
        # counts (and weights) of the neighbourhood incl. the stencil margin
        for j in range(S):
            for i in range(S):
                n, f = _count(ring, head, ye - R + j, xe - R + i, k, te, wlim, w_inv, depth)
                N[i, j] = n
                F[i, j] = f
        sx2 = 0.0
        sy2 = 0.0
        sxy = 0.0
        sxt = 0.0
        syt = 0.0
        vx = 0.0
        vy = 0.0
        if faithful:
            gxs = 0.0
            gys = 0.0
            if gradient == SAVITZKY_GOLAY:
                for j in range(S):
                    for i in range(S):
                        gxs += (i - R) * N[i, j]
                        gys += (j - R) * N[i, j]
                gxs /= sg_norm
                gys /= sg_norm
            gxc = 0.0
            gyc = 0.0
            ntc = 0.0
            for j in range(d, S - d):
                for i in range(d, S - d):
                    if gradient == BACKWARD:
                        gx = float(N[i, j] - N[i - 1, j])
                        gy = float(N[i, j] - N[i, j - 1])
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
            qq = sx2 * sy2 - sxy * sxy
            disc = np.sqrt((sx2 - sy2) * (sx2 - sy2) + 4.0 * sxy * sxy)
            lam1 = 0.5 * (pp + disc)
            lam2 = 0.5 * (pp - disc)
            if lam1 < eig_threshold:
                vx = 0.0
                vy = 0.0
            elif lam2 < eig_threshold:
                g2 = gxc * gxc + gyc * gyc
                if g2 > 0.0:
                    vx = -gxc * ntc / g2
                    vy = -gyc * ntc / g2
            else:
                vx = (sxy * syt - sy2 * sxt) / qq
                vy = (sxy * sxt - sx2 * syt) / qq
            v = np.sqrt(vx * vx + vy * vy)
            if speed_control:
                speed_state[0] = (1.0 - mix) * speed_state[0] + mix * v
                if v > speed_state[0] * max_factor:
                    continue
            if v == 0.0 or not np.isfinite(v):
                continue
        else:
            m = 0
            sb = 0.0
            if gradient == SAVITZKY_GOLAY:
                # least-squares plane F = a + gx*u + gy*w over pixels with events (centred)
                s1 = 0.0
                su = 0.0
                sw = 0.0
                suu = 0.0
                sww = 0.0
                suw = 0.0
                sf = 0.0
                suf = 0.0
                swf = 0.0
                for j in range(S):
                    for i in range(S):
                        if N[i, j] > 0:
                            u = float(i - R)
                            w = float(j - R)
                            f = F[i, j]
                            s1 += 1.0
                            su += u
                            sw += w
                            suu += u * u
                            sww += w * w
                            suw += u * w
                            sf += f
                            suf += u * f
                            swf += w * f
                            sb += N[i, j] * w_inv * 1e6
                            m += 1
                if m < 3:
                    continue
                # centre the sums
                cuu = suu - su * su / s1
                cww = sww - sw * sw / s1
                cuw = suw - su * sw / s1
                cuf = suf - su * sf / s1
                cwf = swf - sw * sf / s1
                det = cuu * cww - cuw * cuw
                if det <= 1e-9 * (cuu * cww + 1e-300):
                    continue  # collinear support: no plane
                gx = (cww * cuf - cuw * cwf) / det
                gy = (cuu * cwf - cuw * cuf) / det
                g2 = gx * gx + gy * gy
                if g2 <= 0.0:
                    continue
                bt = sb / m
                vx = gx * bt / g2
                vy = gy * bt / g2
            else:
                for j in range(d, S - d):
                    for i in range(d, S - d):
                        if N[i, j] == 0:
                            continue
                        gx, okx = _deriv(F, N, i, j, 1, 0, gradient)
                        if not okx:
                            continue
                        gy, oky = _deriv(F, N, i, j, 0, 1, gradient)
                        if not oky:
                            continue
                        b = N[i, j] * w_inv * 1e6  # -F_t in 1/s
                        sx2 += gx * gx
                        sy2 += gy * gy
                        sxy += gx * gy
                        sxt += gx * b
                        syt += gy * b
                        m += 1
                if m < 2:
                    continue
                pp = sx2 + sy2
                disc = np.sqrt((sx2 - sy2) * (sx2 - sy2) + 4.0 * sxy * sxy)
                lam1 = 0.5 * (pp + disc)
                lam2 = 0.5 * (pp - disc)
                if not lam1 > 0.0:
                    continue
                if lam2 >= eig_ratio * lam1 and lam2 > 0.0:
                    qq = sx2 * sy2 - sxy * sxy
                    vx = (sy2 * sxt - sxy * syt) / qq
                    vy = (sx2 * syt - sxy * sxt) / qq
                else:
                    # least squares restricted to the dominant eigenvector (normal flow)
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
                    vx = ex * proj
                    vy = ey * proj
            v = np.sqrt(vx * vx + vy * vy)
            if not np.isfinite(v) or v == 0.0 or v > max_speed_pxs:
                continue
            if speed_control:
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
