"""Plain numpy reference of the per-event part of the ``ttc`` kernel (region B and tau)."""

from __future__ import annotations

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


def ground_constant_naive(kg, tol, rate, min_events) -> tuple[float, int]:
    """The ground constant K after the sequence ``kg`` (tau * dy per event), and the number of
    events it has taken: a running median by multiplicative sign steps of max(rate, 1/(n+2)),
    over every positive kg until ``min_events``, then only over kg within 2 tol of K."""
    k, n = 0.0, 0
    for v in kg:
        v = float(v)
        if not v > 0.0:
            continue
        if n == 0:
            k, n = v, 1
        elif n < min_events or abs(v - k) <= 2.0 * tol * k:
            step = max(rate, 1.0 / (n + 2.0))
            if v > k:
                k *= 1.0 + step
            elif v < k:
                k *= 1.0 - step
            n += 1
    return k, n


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
