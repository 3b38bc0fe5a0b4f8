"""Slow obvious reference of evchain.kernels.plane_flow (plain python + numpy.linalg)."""

from __future__ import annotations

import math

import numpy as np

VARIANTS = ("single", "iterative", "robust", "original", "savitzky_golay")


def _explicit(pts):
    """Least squares t = a x + b y + c via numpy; None when the x-y points are collinear."""
    P = np.asarray(pts, float)
    if len(P) < 3:
        return None
    xy = P[:, :2] - P[:, :2].mean(0)
    cov = xy.T @ xy
    if cov[0, 0] <= 0 or cov[1, 1] <= 0:
        return None
    if np.linalg.det(cov) <= 1e-9 * cov[0, 0] * cov[1, 1]:
        return None
    A = np.column_stack([P[:, 0], P[:, 1], np.ones(len(P))])
    sol = np.linalg.lstsq(A, P[:, 2], rcond=None)[0]
    return sol  # a, b, c


def _homogeneous(pts):
    """Smallest-eigenvector plane through the centroid; (n, d) with n_t >= 0, or None."""
    P = np.asarray(pts, float)
    if len(P) < 3:
        return None
    c = P.mean(0)
    Q = P - c
    cov = Q[:, :2].T @ Q[:, :2]
    if cov[0, 0] <= 0 or cov[1, 1] <= 0 or np.linalg.det(cov) <= 1e-9 * cov[0, 0] * cov[1, 1]:
        return None
    w, V = np.linalg.eigh(Q.T @ Q)
    if w[1] - w[0] <= 1e-12 * abs(w[2]) or np.ptp(w) == 0:
        return None
    n = V[:, 0]
    if n[2] < 0:
        n = -n
    return n, float(n @ c)


def _iterate(pts, fit, resid, params_of, th1, th2, max_iter):
    pts = list(pts)
    sol = fit(pts)
    if sol is None:
        return None
    for _ in range(max_iter):
        keep = [q for q in pts if abs(resid(sol, q)) <= th2]
        if len(keep) == len(pts):
            break
        if len(keep) <= 3:
            return None
        pts = keep
        new = fit(pts)
        if new is None:
            return None
        change = np.max(np.abs(params_of(new) - params_of(sol)))
        sol = new
        if change < th1:
            break
    return sol


def _spread_at_least(offsets, min_spread):
    """The smallest eigenvalue of the offsets' covariance is >= min_spread^2: n^2 (cov -
    min_spread^2 I) is positive semi-definite (diagonal and determinant >= 0). The offsets are
    integers, so the n^2-scaled moments are exact integers and a tie on the bound is decided
    by one rounding of n^2 min_spread^2 only."""
    n = len(offsets)
    sx = sum(dx for dx, _ in offsets)
    sy = sum(dy for _, dy in offsets)
    s = n * n * (min_spread * min_spread)
    a = n * sum(dx * dx for dx, _ in offsets) - sx * sx - s
    c = n * sum(dy * dy for _, dy in offsets) - sy * sy - s
    b = n * sum(dx * dy for dx, dy in offsets) - sx * sy
    return a >= 0 and c >= 0 and a * c >= b * b


def _sg(win, valid):
    size = win.shape[0]
    sx, nx, sy, ny = 0.0, 0, 0.0, 0
    for i in range(size):
        for j in range(size):
            for k in range(size):
                if k > j and valid[i, j] and valid[i, k]:
                    sx += (win[i, k] - win[i, j]) * 1e-6 / (k - j)
                    nx += 1
                if k > i and valid[i, j] and valid[k, j]:
                    sy += (win[k, j] - win[i, j]) * 1e-6 / (k - i)
                    ny += 1
    if nx == 0 or ny == 0:
        return None
    return sx / nx, sy / ny


def _estimate(ts, xi, yi, ti, pi, width, height, variant, r, window_us, min_points, th1,
              th2, max_iter, min_spread, centre_check):
    """One event's fit and why it failed: ((a, b) = gradient (s/px), or (vx, vy) for
    ``original``; None), or (None, the kernel's WHY_NO_FLOW name)."""
    pts = []
    for yy in range(yi - r, yi + r + 1):
        for xx in range(xi - r, xi + r + 1):
            tt = ts.get((pi, xx, yy))
            if tt is not None and ti - tt <= window_us:
                pts.append((xx - xi, yy - yi, (tt - ti) * 1e-6))
    if len(pts) < max(min_points, 3):
        return None, "too_few_neighbours"
    if min_spread > 0 and not _spread_at_least([q[:2] for q in pts], min_spread):
        return None, "too_narrow"
    if variant == "savitzky_golay":
        win = np.zeros((2 * r + 1, 2 * r + 1))
        valid = np.zeros_like(win, bool)
        for (dx, dy, dt) in pts:
            win[dy + r, dx + r] = ti + round(dt * 1e6)
            valid[dy + r, dx + r] = True
        g = _sg(win, valid)
        if g is None:
            return None, "no_plane"
        gx, gy = g
        P = np.asarray(pts, float)
        c = np.mean(P[:, 2] - gx * P[:, 0] - gy * P[:, 1])
        if centre_check and abs(c) > th2:
            return None, "centre_check"
        return (gx, gy), None
    if variant in ("single", "iterative"):
        if variant == "single":
            sol = _explicit(pts)
        else:
            sol = _iterate(pts, _explicit, lambda s, q: q[2] - (s[0] * q[0] + s[1] * q[1]
                                                                + s[2]),
                           lambda s: np.asarray(s), th1, th2, max_iter)
        if sol is None:
            return None, "no_plane"
        if centre_check and abs(sol[2]) > th2:
            return None, "centre_check"
        return (sol[0], sol[1]), None
    sol = _iterate(pts, _homogeneous, lambda s, q: s[0] @ np.asarray(q) - s[1],
                   lambda s: s[0], th1, th2, max_iter)
    if sol is None:
        return None, "no_plane"
    n = sol[0]
    if n[2] <= 0:
        return None, "no_plane"
    if centre_check and abs(sol[1]) > th2:
        return None, "centre_check"
    if variant == "original":
        if n[0] == 0 or n[1] == 0:
            return None, "no_plane"
        return (-n[2] / n[0], -n[2] / n[1]), None
    return (-n[0] / n[2], -n[1] / n[2]), None


def plane_flow_naive(x, y, t, p, width, height, variant="single", r=2, window_us=80_000,
                     refractory_us=0, margin=None, min_points=3, th1=1e-5, th2=0.01,
                     max_speed=1000.0, max_iter=10, min_spread=0.0,
                     centre_check=False, max_window_us=0, slow_px=2.0, refit_failed=True,
                     refractory_updates=True, min_window_us=0, fast_px=4.0, counts=None):
    """Returns (index, vx, vy) lists of the events that got flow.

    Adaptive window (``max_window_us`` > ``window_us``, not ``original``): while the fit says
    the edge moved less than ``slow_px`` px within the window w (|g| slow_px > w), refit with
    w = min(slow_px |g|, max_window_us) if that is longer; with ``refit_failed`` a failed first
    fit is redone once with ``max_window_us``. Refits check the centre against th2 w / window_us.
    The last fit counts. ``refractory_updates`` false: refractory events do not touch the
    surface either. Short window (0 < ``min_window_us`` < ``window_us``, not ``original``): a
    first fit whose edge moved more than ``fast_px`` px within ``window_us`` is redone with
    max(min_window_us, fast_px |g|) instead of any longer refit; it replaces the first fit
    when it succeeds. ``counts`` (a dict, optional) is added to per event: why it got no flow
    (the kernel's WHY_NO_FLOW names; the last fit's reason where there were refits) or
    ``flow``.
    """
    counts = {} if counts is None else counts

    def count(why):
        counts[why] = counts.get(why, 0) + 1

    margin = r if margin is None else margin
    ts = {}
    idx, vxs, vys = [], [], []
    for i in range(len(x)):
        xi, yi, ti, pi = int(x[i]), int(y[i]), int(t[i]), 1 if p[i] > 0 else 0
        prev = ts.get((pi, xi, yi))
        if prev is not None and ti - prev < refractory_us:
            if refractory_updates:  # jAER: the memory still updates
                ts[(pi, xi, yi)] = ti
            count("refractory")
            continue
        ts[(pi, xi, yi)] = ti
        if xi < margin or yi < margin or xi >= width - margin or yi >= height - margin:
            count("border")
            continue
        if variant == "savitzky_golay" and not (xi - r >= 0 and yi - r >= 0
                                                and xi + r < width and yi + r < height):
            count("border")
            continue
        args = (ts, xi, yi, ti, pi, width, height, variant, r)
        rest = (min_points, th1)
        tail = (max_iter, min_spread, centre_check)
        est, why = _estimate(*args, window_us, *rest, th2, *tail)
        shrunk = False
        if 0 < min_window_us < window_us and variant != "original" and est is not None:
            want = fast_px * 1e6 * math.sqrt(est[0] * est[0] + est[1] * est[1])
            if want < window_us and max(min_window_us, math.ceil(want)) < window_us:
                shrunk = True
                w = max(min_window_us, math.ceil(want))
                est = _estimate(*args, w, *rest, th2 * w / window_us, *tail)[0] or est
        if max_window_us > window_us and variant != "original" and not shrunk:
            w = window_us
            for _ in range(4):
                if est is not None:
                    want = slow_px * 1e6 * math.sqrt(est[0] * est[0] + est[1] * est[1])
                    if want <= w:
                        break
                    w_new = max_window_us if want >= max_window_us else int(want)
                elif refit_failed and w == window_us:
                    w_new = max_window_us
                else:
                    break
                if w_new <= w:
                    break
                w = w_new
                est, why = _estimate(*args, w, *rest, th2 * w / window_us, *tail)
        if est is None:
            count(why)
            continue
        if variant == "original":
            vx, vy = est
            if vx * vx + vy * vy > max_speed ** 2:
                count("too_fast")
                continue
            count("flow")
            idx.append(i)
            vxs.append(vx)
            vys.append(vy)
            continue
        gx, gy = est
        g2 = gx * gx + gy * gy
        if g2 == 0 or g2 < (1.0 / max_speed) ** 2:
            count("too_fast")
            continue
        count("flow")
        idx.append(i)
        vxs.append(gx / g2)
        vys.append(gy / g2)
    return np.array(idx, np.int64), np.array(vxs), np.array(vys)
