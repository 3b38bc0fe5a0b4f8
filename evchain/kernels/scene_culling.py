"""Numba kernel of the scene renderer's culling: the boxes a frame may see, nearest first, with
the bounding rectangles of their projections (:func:`frame_boxes`). Array layouts and camera
conventions: :mod:`evchain.kernels.scene_geometry`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from evchain.kernels.scene_geometry import INF

_J = dict(cache=True, error_model="numpy")


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
