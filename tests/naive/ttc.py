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
