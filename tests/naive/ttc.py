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
