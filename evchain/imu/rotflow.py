"""The motion field of a rotating pinhole camera (Longuet-Higgins & Prazdny 1980).

Camera axes x right, y down, z forward (the optical axis); pixel (x, y) with focal length ``f``
and principal point ``(cx, cy)`` in px, normalised coordinates ``X = (x - cx) / f``,
``Y = (y - cy) / f``. A camera turning at ``w = (wx, wy, wz)`` rad/s (right-hand rule about its
axes) sees every scene point, whatever its depth, move at

    u = f (X Y wx - (1 + X^2) wy + Y wz)
    v = f ((1 + Y^2) wx - X Y wy - X wz)        (px/s)

so a pan to the right (wy > 0) moves the image left, a tilt up (wx > 0) moves it down, and a
clockwise roll seen from behind (wz > 0) turns it counter-clockwise on screen.
"""

from __future__ import annotations

import numpy as np


def flow_matrix(x, y, f: float, cx: float, cy: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``(a_u, a_v)``, each ``[..., 3]``, with ``u = a_u . w`` and ``v = a_v . w``."""
    X = (np.asarray(x, np.float64) - cx) / f
    Y = (np.asarray(y, np.float64) - cy) / f
    a_u = np.stack([f * X * Y, -f * (1.0 + X * X), f * Y], axis=-1)
    a_v = np.stack([f * (1.0 + Y * Y), -f * X * Y, -f * X], axis=-1)
    return a_u, a_v


def rotational_flow(x, y, w, f: float, cx: float, cy: float) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` px/s at pixels ``(x, y)`` for angular velocities ``w`` (``[..., 3]`` rad/s,
    broadcast against ``x, y``)."""
    X = (np.asarray(x, np.float64) - cx) / f
    Y = (np.asarray(y, np.float64) - cy) / f
    w = np.asarray(w, np.float64)
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    u = f * (X * Y * wx - (1.0 + X * X) * wy + Y * wz)
    v = f * ((1.0 + Y * Y) * wx - X * Y * wy - X * wz)
    return u, v
