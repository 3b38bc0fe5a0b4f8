"""Plain numpy reference of the per-event part of the ``ttc`` kernel (region B and tau)."""

from __future__ import annotations

import math

import numpy as np


def event_tau_naive(px, py, vx, vy, fx, fy, half_width, min_below, min_dist, min_speed,
                    max_speed, min_tau, max_tau) -> np.ndarray:
    """Vectorised: tau = (p - foe).v / |v|^2 where the event qualifies, else -1."""
    px, py, vx, vy = (np.asarray(a, np.float64) for a in (px, py, vx, vy))
    rx, ry = px - fx, py - fy
    speed = np.hypot(vx, vy)
    d = rx * vx + ry * vy
    ok = ((ry >= min_below) & (np.abs(rx) <= half_width) & (np.hypot(rx, ry) >= min_dist)
          & (speed > 0) & (speed >= min_speed) & (speed <= max_speed) & (d > 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(ok, d / np.where(speed > 0, speed * speed, 1.0), -1.0)
    ok &= (tau >= min_tau) & (tau <= max_tau)
    return np.where(ok, tau, -1.0)


def ground_constant_naive(kg, t_us, tol, memory_us, k_min=0.01, width=0.02,
                          bins=1024) -> tuple[float, int]:
    """The ground constant K after the votes ``kg`` (tau * dy) at times ``t_us``, and the number
    of votes: every positive kg whose bin floor((ln kg - ln k_min) / width) lies in [0, bins)
    votes with weight exp(t / memory) (only the ratios matter); K is the weighted mean bin
    centre (in ln) of the window of 2 round(ln(1 + tol) / width) + 1 bins with the most weight
    (the first of equals), 0 without votes."""
    ln_min = math.log(k_min)
    kg = np.asarray(kg, np.float64)
    t = np.asarray(t_us, np.float64)
    ok = kg > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        b = np.floor((np.log(np.where(ok, kg, 1.0)) - ln_min) / width)
    ok &= (b >= 0) & (b < bins)
    if not ok.any():
        return 0.0, 0
    w = np.exp((t[ok] - t[ok].max()) / memory_us)
    h = np.bincount(b[ok].astype(np.int64), w, minlength=bins)
    win = 2 * int(round(math.log(1.0 + tol) / width)) + 1
    sums = [h[j:j + win].sum() for j in range(max(1, bins - win + 1))]
    j = int(np.argmax(sums))
    c = np.arange(j, min(j + win, bins)) + 0.5
    k = math.exp(ln_min + width * float((h[j:j + win] * c).sum() / h[j:j + win].sum()))
    return k, int(ok.sum())


def baseline_tau_naive(last_t, px, py, nx, ny, d0, ti, max_px, max_age_us) -> float:
    """tau from the pixel the edge through p crossed earliest within the walk: step back
    k = 1..max_px px against the unit normal n (nearest pixel; skip p's own pixel), stop at
    the first pixel outside the image, not strictly older than the previous one, older than
    ``max_age_us`` or not between the FOE and p; tau = (d0 - dd) (ti - tq) / dd for the last
    pixel passed (dd its distance behind p along n), -1 when there is none."""
    h, w = last_t.shape
    own = (int(np.floor(px + 0.5)), int(np.floor(py + 0.5)))
    tprev, tau = ti, -1.0
    for k in range(1, max_px + 1):
        q = (int(np.floor(px - k * nx + 0.5)), int(np.floor(py - k * ny + 0.5)))
        if not (0 <= q[0] < w and 0 <= q[1] < h):
            break
        if q == own:
            continue
        tq = last_t[q[1], q[0]]
        if not tq < tprev or ti - tq > max_age_us:
            break
        dd = (px - q[0]) * nx + (py - q[1]) * ny
        if not (dd > 0 and d0 - dd > 0):
            break
        tau, tprev = (d0 - dd) * (ti - tq) * 1e-6 / dd, tq
    return tau
