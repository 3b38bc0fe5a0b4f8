"""Numba kernels of the scene renderer's culling: the boxes a frame may see, nearest first, with
the bounding rectangles of their projections (:func:`frame_boxes`), and the sample columns of
one sample row whose rays can meet a box (:func:`box_span`). Array layouts and camera
conventions: :mod:`evchain.kernels.scene_geometry`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from evchain.kernels.scene_geometry import INF

_J = dict(cache=True, error_model="numpy")
_I = dict(cache=True, error_model="numpy", inline="always")   # helpers of the hot loops


@njit(**_J)
def frame_boxes(boxes, pos, rot, f, cx, cy, width, height, order, minz, bbox):
    """Boxes whose projection (clipped at a tiny near plane) may touch the image.

    Writes their indices into order[:nvis] sorted by their lower depth bound (nearest corner
    depth, >= 0), which goes into minz[box], and the bounding rectangle of the projection in
    normalised coordinates into bbox[box] = (x0, x1, y0, y1); returns nvis."""
    n = boxes.shape[0]
    zn = 1e-4
    key = np.full(n, INF)
    cz = np.empty(8)
    cxp = np.empty(8)
    cyp = np.empty(8)
    nvis = 0
    for b in range(n):
        for c in range(8):
            wx = boxes[b, 3] if (c & 1) else boxes[b, 0]
            wy = boxes[b, 4] if (c & 2) else boxes[b, 1]
            wz = boxes[b, 5] if (c & 4) else boxes[b, 2]
            rx = wx - pos[0]
            ry = wy - pos[1]
            rz = wz - pos[2]
            cxp[c] = rot[0, 0] * rx + rot[1, 0] * ry + rot[2, 0] * rz
            cyp[c] = rot[0, 1] * rx + rot[1, 1] * ry + rot[2, 1] * rz
            cz[c] = rot[0, 2] * rx + rot[1, 2] * ry + rot[2, 2] * rz
        if cz.max() < zn:
            continue
        x0 = INF
        x1 = -INF
        y0 = INF
        y1 = -INF
        for c in range(8):
            if cz[c] >= zn:
                u = cxp[c] / cz[c]
                v = cyp[c] / cz[c]
                x0 = min(x0, u)
                x1 = max(x1, u)
                y0 = min(y0, v)
                y1 = max(y1, v)
        # edges crossing the near plane (corners differing in one bit)
        for c in range(8):
            for bit in (1, 2, 4):
                e = c | bit
                if e == c:
                    continue
                za = cz[c]
                zb = cz[e]
                if (za - zn) * (zb - zn) < 0.0:
                    a = (zn - za) / (zb - za)
                    u = (cxp[c] + a * (cxp[e] - cxp[c])) / zn
                    v = (cyp[c] + a * (cyp[e] - cyp[c])) / zn
                    x0 = min(x0, u)
                    x1 = max(x1, u)
                    y0 = min(y0, v)
                    y1 = max(y1, v)
        if (f * x1 + cx + 1.0 < -1.0 or f * y1 + cy + 1.0 < -1.0
                or f * x0 + cx - 1.0 > width or f * y0 + cy - 1.0 > height):
            continue
        zmin = cz.min()
        minz[b] = zmin if zmin > 0.0 else 0.0
        bbox[b, 0] = x0
        bbox[b, 1] = x1
        bbox[b, 2] = y0
        bbox[b, 3] = y1
        key[b] = minz[b]
        nvis += 1
    srt = np.argsort(key)
    for q in range(nvis):
        order[q] = srt[q]
    return nvis


@njit(**_I)
def _span_corner(qx, qy, r0, r1, rr, xh0, xh1):
    return (qx * r0 + qy * r1) / rr, qx * xh0 + qy * xh1


@njit(**_I)
def _span_vertex(t, u, ta, tb, lo, hi):
    if t >= ta and t <= tb:
        xb = u / t
        return min(lo, xb), max(hi, xb)
    return lo, hi


@njit(**_I)
def _span_edge(t0, u0, t1, u1, ta, tb, lo, hi):
    for lv in range(2):
        level = ta if lv == 0 else tb
        if (t0 - level) * (t1 - level) < 0.0:
            s = (level - t0) / (t1 - t0)
            xb = (u0 + s * (u1 - u0)) / level
            lo = min(lo, xb)
            hi = max(hi, xb)
    return lo, hi


@njit(**_I)
def box_span(bx0, by0, bx1, by1, ox, oy, xh0, xh1, r0, r1, ta, tb, f, cx, k, ncols):
    """Sample columns [c0, c1] of one sample row whose rays can meet a box between the ray
    parameters ta and tb (conservative, with a margin of two samples; c0 > c1: none).

    The rays of a row are o + t (xb X + R) with X the camera's horizontal x axis (no roll) and
    R = yb Y + Z, so X is orthogonal to R: in the ground-plane projection a point q lies on the
    ray with t = (q - o).R_h / |R_h|^2 and xb = (q - o).X_h / t. The box's footprint clipped to
    ta <= t <= tb is a convex polygon, and xb (linear-fractional in q) takes its extremes at
    the polygon's vertices."""
    rr = r0 * r0 + r1 * r1
    if rr < 1e-12 or not (ta <= tb):
        return 0, ncols - 1
    # corners (x0, y0), (x1, y0), (x1, y1), (x0, y1): ray parameter t and lateral u = xb t
    t0, u0 = _span_corner(bx0 - ox, by0 - oy, r0, r1, rr, xh0, xh1)
    t1, u1 = _span_corner(bx1 - ox, by0 - oy, r0, r1, rr, xh0, xh1)
    t2, u2 = _span_corner(bx1 - ox, by1 - oy, r0, r1, rr, xh0, xh1)
    t3, u3 = _span_corner(bx0 - ox, by1 - oy, r0, r1, rr, xh0, xh1)
    lo = INF
    hi = -INF
    lo, hi = _span_vertex(t0, u0, ta, tb, lo, hi)
    lo, hi = _span_vertex(t1, u1, ta, tb, lo, hi)
    lo, hi = _span_vertex(t2, u2, ta, tb, lo, hi)
    lo, hi = _span_vertex(t3, u3, ta, tb, lo, hi)
    # edges crossing the levels t = ta and t = tb
    lo, hi = _span_edge(t0, u0, t1, u1, ta, tb, lo, hi)
    lo, hi = _span_edge(t1, u1, t2, u2, ta, tb, lo, hi)
    lo, hi = _span_edge(t2, u2, t3, u3, ta, tb, lo, hi)
    lo, hi = _span_edge(t3, u3, t0, u0, ta, tb, lo, hi)
    if lo > hi:
        return 1, 0
    lo = max(lo, -1e6)
    hi = min(hi, 1e6)
    c0 = int(math.floor((lo * f + cx + 0.5) * k - 0.5)) - 2
    c1 = int(math.ceil((hi * f + cx + 0.5) * k - 0.5)) + 2
    return max(c0, 0), min(c1, ncols - 1)
