"""Driving lines (trajectories): straight and circular-arc segments, parameterised by arc length.

The ego car's driving line is a chain of segments starting at (0, lane_offset) heading along
world x; the road centre lies at a fixed lateral offset from it. The kernels use the table
returned by :func:`segment_table` (see :mod:`evchain.kernels.scene_geometry`).
"""

from __future__ import annotations

import math

import numpy as np


def segment_table(x0: float, y0: float, heading: float,
                  pieces: list[tuple[float, float]]) -> np.ndarray:
    """Segments [M, 11] (x0, y0, heading0, length, kappa, s0, xc, yc, cos h0, sin h0, phi0) from
    (length, kappa) pieces."""
    rows = []
    x, y, h, s = x0, y0, heading, 0.0
    for length, kap in pieces:
        if length <= 0:
            raise ValueError(f"segment length must be > 0, got {length}")
        if kap == 0.0:
            rows.append((x, y, h, length, 0.0, s, 0.0, 0.0, math.cos(h), math.sin(h), 0.0))
            x, y = x + length * math.cos(h), y + length * math.sin(h)
        else:
            xc, yc = x - math.sin(h) / kap, y + math.cos(h) / kap
            rows.append((x, y, h, length, kap, s, xc, yc, math.cos(h), math.sin(h),
                         math.atan2(y - yc, x - xc)))
            h1 = h + kap * length
            x, y = x + (math.sin(h1) - math.sin(h)) / kap, y - (math.cos(h1) - math.cos(h)) / kap
            h = h1
        s += length
    return np.array(rows, dtype=np.float64)


def path_points(segs: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Positions [n, 2] and headings [n] of the driving line at arc lengths s (plain numpy)."""
    s = np.atleast_1d(np.asarray(s, float))
    k = np.clip(np.searchsorted(segs[:, 5], s, side="right") - 1, 0, len(segs) - 1)
    x0, y0, h0, _, kap, s0 = (segs[k, i] for i in range(6))
    u = s - s0
    straight = kap == 0
    safe = np.where(straight, 1.0, kap)
    h = h0 + kap * u
    x = np.where(straight, x0 + u * np.cos(h0), x0 + (np.sin(h) - np.sin(h0)) / safe)
    y = np.where(straight, y0 + u * np.sin(h0), y0 - (np.cos(h) - np.cos(h0)) / safe)
    return np.stack([x, y], axis=1), h
