"""Slow, obvious reference of the ``lk_flow`` kernel: plain Python over events, deques as FIFOs.

Same semantics as ``evchain.kernels.lk_flow.lk_flow_run`` (see its docstring and
docs/explanation/lk_flow.md), written independently for comparison in tests.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

MARGIN = {"backward": 1, "central": 1, "central2": 2, "savitzky_golay": 0}
NORM = {"backward": 1.0, "central": 2.0, "central2": 12.0}


def lk_flow_naive(x, y, t, p, width, height, *, search_distance=2, window_us=80_000,
                  refractory_us=150_000, gradient="savitzky_golay", mode="calibrated",
                  eig_threshold=1.0, eig_ratio=0.1, speed_control=True, speed_control_mix=1e-3,
                  max_speed_factor=2.0, max_speed_pxs=1e5, refit_tolerance=0.25,
                  centre_check_px=0.5, fifo_depth=8, max_window_us=0, slow_px=2.0,
                  min_window_us=0, fast_px=8.0):
    """Return (index, vx, vy) lists of the emitted events.

    Speed-adaptive window (calibrated, ``max_window_us`` > ``window_us``): estimate with
    ``window_us``; while the estimate fails or its edge crosses fewer than ``slow_px`` px within
    the window, estimate again with min(max_window_us, slow_px / speed) (max_window_us after a
    failure), 3 estimates at most; a new estimate replaces the previous one only if it
    succeeded and its edge crosses fewer than ``slow_px`` px within the previous window.

    Two time scales (calibrated, 0 < ``min_window_us`` < ``window_us``): first estimate with
    ``min_window_us``; if that succeeds and its edge crosses at least ``fast_px`` px within
    ``min_window_us``, it is the event's flow; else everything above, as without it."""
    r = search_distance
    d = MARGIN[gradient]
    margin = r + d
    faithful = mode == "faithful"
    fifo: dict[tuple[int, int, int], deque] = {}
    avg = 0.0
    avg_init = False
    out_i, out_vx, out_vy = [], [], []

    def in_window(age, win):
        return age <= win if faithful else age < win

    def count(xx, yy, k, now, win=window_us):
        q = fifo.get((xx, yy, k), ())
        ages = [now - ts for ts in q if in_window(now - ts, win)]
        return len(ages), (1.0 - max(ages) / win) if ages else 0.0

    def estimate(xe, ye, k, te, win):
        """Calibrated flow (vx, vy) of the event with window ``win``, or None."""
        N, F = {}, {}
        for dy in range(-margin, margin + 1):
            for dx in range(-margin, margin + 1):
                N[dx, dy], F[dx, dy] = count(xe + dx, ye + dy, k, te, win)
        res = _calibrated(N, F, hood, gradient, win, eig_ratio, refit_tolerance)
        if res is None:
            return None
        if centre_check_px > 0 and _centre_offset(N, F, hood, *res, win) > centre_check_px:
            return None
        v = math.hypot(*res)
        if not math.isfinite(v) or v == 0 or v > max_speed_pxs:
            return None
        return res

    hood = [(dx, dy) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]

    for e in range(len(t)):
        xe, ye, te = int(x[e]), int(y[e]), int(t[e])
        k = 1 if p[e] > 0 else 0
        inside = margin <= xe < width - margin and margin <= ye < height - margin
        if faithful and not inside:
            continue
        q = fifo.setdefault((xe, ye, k), deque(maxlen=fifo_depth))
        prev = q[-1] if q else None
        q.append(te)
        if not inside:
            continue
        if prev is not None and te - prev < refractory_us:
            continue
        if faithful:
            N = {}
            for dy in range(-margin, margin + 1):
                for dx in range(-margin, margin + 1):
                    N[dx, dy] = count(xe + dx, ye + dy, k, te)[0]
            vx, vy = _faithful(N, hood, r, gradient, eig_threshold)
            v = math.hypot(vx, vy)
            if speed_control:
                avg = (1 - speed_control_mix) * avg + speed_control_mix * v
                if v > avg * max_speed_factor:
                    continue
            if v == 0:
                continue
        else:
            res = None
            if 0 < min_window_us < window_us:
                res = estimate(xe, ye, k, te, min_window_us)
                if res is not None and math.hypot(*res) * min_window_us < fast_px * 1e6:
                    res = None  # too slow for the short window
            short = res is not None
            if not short:
                res = estimate(xe, ye, k, te, window_us)
            win = window_us
            for _ in range(2 if max_window_us > window_us and not short else 0):
                if res is None:
                    nxt = max_window_us
                else:
                    s = math.hypot(*res)
                    if s * win >= slow_px * 1e6:
                        break
                    nxt = min(max_window_us, math.ceil(slow_px * 1e6 / s))
                if nxt <= win:
                    break
                res2 = estimate(xe, ye, k, te, nxt)
                if res2 is None or math.hypot(*res2) * win >= slow_px * 1e6:
                    break
                res, win = res2, nxt
            if res is None:
                continue
            vx, vy = res
            v = math.hypot(vx, vy)
            if speed_control:
                if not avg_init:
                    avg, avg_init = v, True
                else:
                    avg = (1 - speed_control_mix) * avg + speed_control_mix * v
                if v > avg * max_speed_factor:
                    continue
        out_i.append(e)
        out_vx.append(vx)
        out_vy.append(vy)
    return out_i, out_vx, out_vy


def _faithful(N, hood, r, gradient, thr):
    if gradient == "savitzky_golay":
        sg = sum(i * i for (i, _) in hood)
        gx_all = sum(i * N[i, j] for (i, j) in hood) / sg
        gy_all = sum(j * N[i, j] for (i, j) in hood) / sg
    rows = []
    for (i, j) in hood:
        if gradient == "backward":
            # jAER differences backwards along its own y axis, which points up
            g = (N[i, j] - N[i - 1, j], -(N[i, j] - N[i, j + 1]))
        elif gradient == "central":
            g = (N[i + 1, j] - N[i - 1, j], N[i, j + 1] - N[i, j - 1])
        elif gradient == "central2":
            g = (N[i - 2, j] - 8 * N[i - 1, j] + 8 * N[i + 1, j] - N[i + 2, j],
                 N[i, j - 2] - 8 * N[i, j - 1] + 8 * N[i, j + 1] - N[i, j + 2])
        else:
            g = (gx_all, gy_all)
        norm = 1.0 / r if gradient == "savitzky_golay" else NORM[gradient]
        rows.append((float(g[0]), float(g[1]), N[i, j] * norm * 20.0, (i, j) == (0, 0)))
    A = np.array([[a, b] for a, b, _, _ in rows])
    nt = np.array([c for _, _, c, _ in rows])
    M = A.T @ A
    lam2, lam1 = np.linalg.eigvalsh(M)
    if lam1 < thr:
        return 0.0, 0.0
    if lam2 < thr:
        gx, gy, ntc, _ = next(row for row in rows if row[3])
        g2 = gx * gx + gy * gy
        return (0.0, 0.0) if g2 == 0 else (-gx * ntc / g2, -gy * ntc / g2)
    v = -np.linalg.solve(M, A.T @ nt)
    return float(v[0]), float(v[1])


def _one_deriv(F, N, i, j, di, dj, gradient):
    def ok(a, b):
        return N.get((a, b), 0) > 0

    if not ok(i, j):
        return None
    back, fwd = ok(i - di, j - dj), ok(i + di, j + dj)
    if gradient == "central2" and back and fwd and ok(i - 2 * di, j - 2 * dj) \
            and ok(i + 2 * di, j + 2 * dj):
        return (F[i - 2 * di, j - 2 * dj] - 8 * F[i - di, j - dj] + 8 * F[i + di, j + dj]
                - F[i + 2 * di, j + 2 * dj]) / 12.0
    if gradient != "backward" and back and fwd:
        return 0.5 * (F[i + di, j + dj] - F[i - di, j - dj])
    if back:
        return F[i, j] - F[i - di, j - dj]
    if fwd:
        return F[i + di, j + dj] - F[i, j]
    return None


def _centre_offset(N, F, hood, vx, vy, window_us):
    """Distance (px along the normal) of the centre's onset from the plane of slope
    g = v / (W |v|^2) through the other active pixels (mean offset)."""
    v2 = vx * vx + vy * vy
    if not v2 > 0:
        return math.inf
    g = np.array([vx, vy]) / (window_us * 1e-6) / v2
    others = [F[q] - g @ np.array(q) for q in hood if q != (0, 0) and N[q] > 0]
    if not others:
        return math.inf
    return abs(F[0, 0] - np.mean(others)) / math.hypot(*g)


def _plane_fit(pts, F):
    """(c, g) of the least-squares plane F = c + g . (i, j), or None if degenerate."""
    if len(pts) < 3:
        return None
    P = np.array(pts, float)
    Pc = P - P.mean(axis=0)
    C = Pc.T @ Pc
    if np.linalg.det(C) <= 1e-9 * (C[0, 0] * C[1, 1] + 1e-300):
        return None
    f = np.array([F[q] for q in pts])
    g = np.linalg.solve(C, Pc.T @ (f - f.mean()))
    c = f.mean() - g @ P.mean(axis=0)
    return c, g


def _ls(rows, rate, eig_ratio):
    A = np.array(rows)
    M = A.T @ A
    lam2, lam1 = np.linalg.eigvalsh(M)
    if not lam1 > 0:
        return None
    Atb = A.T @ np.full(len(rows), rate)
    if lam2 > 0 and lam2 >= eig_ratio * lam1:
        return np.linalg.solve(M, Atb)
    e1 = np.linalg.eigh(M)[1][:, 1]
    return e1 * (e1 @ Atb) / lam1


def _calibrated(N, F, hood, gradient, window_us, eig_ratio, tol):
    rate = 1.0 / (window_us * 1e-6)  # -dF/dt of every active pixel, 1/s
    if gradient == "savitzky_golay":
        pts = [(i, j) for (i, j) in hood if N[i, j] > 0]
        fit = _plane_fit(pts, F)
        if fit is None or not fit[1] @ fit[1] > 0:
            return None
        c, g = fit
        if tol > 0:
            near = [q for q in pts if abs(F[q] - c - g @ np.array(q)) <= tol * np.hypot(*g)]
            if len(near) < len(pts):
                fit = _plane_fit(near, F)
                if fit is None or not fit[1] @ fit[1] > 0:
                    return None
                c, g = fit
        g2 = g @ g
        return float(g[0] * rate / g2), float(g[1] * rate / g2)
    rows = []
    for (i, j) in hood:
        if N[i, j] == 0:
            continue
        gx = _one_deriv(F, N, i, j, 1, 0, gradient)
        gy = _one_deriv(F, N, i, j, 0, 1, gradient)
        if gx is None or gy is None:
            continue
        rows.append((gx, gy))
    if len(rows) < 2:
        return None
    v = _ls(rows, rate, eig_ratio)
    if v is None:
        return None
    if tol > 0:
        good = [r for r in rows if abs((r[0] * v[0] + r[1] * v[1]) / rate - 1) <= tol]
        if len(good) < len(rows):
            if len(good) < 2:
                return None
            v = _ls(good, rate, eig_ratio)
            if v is None:
                return None
    return float(v[0]), float(v[1])
