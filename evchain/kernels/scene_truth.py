"""Numba kernels of the simulator's exact ground truth: depth, motion field and the object seen
at any pixel position and time, by tracing one ray against the ground and every box (the same
slab test as the renderer). Array layouts: :mod:`evchain.kernels.scene_geometry`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from evchain.kernels.scene_geometry import INF, camera_state, flow_at

_J = dict(cache=True, error_model="numpy")
_I = dict(cache=True, error_model="numpy", inline="always")   # helpers of the hot loops


@njit(**_I)
def trace(ox, oy, oz, dx, dy, dz, boxes):
    """Nearest hit of the ray o + t d (t > 0) among the ground plane z = 0 and the boxes.

    Returns (t, kind, index, face): kind 0 sky, 1 ground, 2 box; face = 2 * axis + (1 if the
    max side of the slab)."""
    tb = INF
    kind = 0
    idx = -1
    face = -1
    if dz < 0.0 and oz > 0.0:
        tb = -oz / dz
        kind = 1
    ix = 1.0 / dx
    iy = 1.0 / dy
    iz = 1.0 / dz
    for b in range(boxes.shape[0]):
        t1 = (boxes[b, 0] - ox) * ix
        t2 = (boxes[b, 3] - ox) * ix
        txn = min(t1, t2)
        txf = max(t1, t2)
        t1 = (boxes[b, 1] - oy) * iy
        t2 = (boxes[b, 4] - oy) * iy
        tyn = min(t1, t2)
        tyf = max(t1, t2)
        t1 = (boxes[b, 2] - oz) * iz
        t2 = (boxes[b, 5] - oz) * iz
        tzn = min(t1, t2)
        tzf = max(t1, t2)
        tn = max(txn, max(tyn, tzn))
        tf = min(txf, min(tyf, tzf))
        if tn <= tf and tn > 0.0 and tn < tb:
            tb = tn
            kind = 2
            idx = b
            if txn >= tyn and txn >= tzn:
                face = 0 if dx > 0 else 1
            elif tyn >= tzn:
                face = 2 if dy > 0 else 3
            else:
                face = 4 if dz > 0 else 5
    return tb, kind, idx, face


@njit(**_J)
def truth_query(x, y, t_s, f, cx, cy, boxes, segs, traj):
    """Exact depth, motion field and object seen at pixel positions and times, one query per
    element; the same ray tracing as the renderer.

    Parameters
    ----------
    x, y : ndarray, float64 [n]
        Pixel positions, px (image x right, y down; pixel centres at integers).
    t_s : ndarray, float64 [n]
        Times, s (runs of equal times share one camera state).
    f, cx, cy : float
        Focal length and principal point, px.
    boxes, segs, traj : ndarray
        The world's boxes and driving line, the trajectory (layouts:
        :mod:`evchain.kernels.scene_geometry`).

    Returns
    -------
    depth : ndarray, float64 [n]
        Depth Z of the surface seen, m (inf: sky).
    vx, vy : ndarray, float64 [n]
        The motion field, px/s.
    obj : ndarray, int64 [n]
        The index of the box seen, -2 for the ground, -1 for the sky (``OBJECT_*`` in
        :mod:`evchain.sim.world`).
    """
    n = x.shape[0]
    depth = np.empty(n)
    vx = np.empty(n)
    vy = np.empty(n)
    obj = np.empty(n, np.int64)
    pos = np.empty(3)
    rot = np.empty((3, 3))
    vc = np.empty(3)
    wc = np.empty(3)
    tprev = np.nan
    for q in range(n):
        if t_s[q] != tprev:
            camera_state(t_s[q], segs, traj, pos, rot, vc, wc)
            tprev = t_s[q]
        xb = (x[q] - cx) / f
        yb = (y[q] - cy) / f
        dx = rot[0, 0] * xb + rot[0, 1] * yb + rot[0, 2]
        dy = rot[1, 0] * xb + rot[1, 1] * yb + rot[1, 2]
        dz = rot[2, 0] * xb + rot[2, 1] * yb + rot[2, 2]
        t, kind, idx, face = trace(pos[0], pos[1], pos[2], dx, dy, dz, boxes)
        depth[q] = t
        obj[q] = idx if kind == 2 else (-2 if kind == 1 else -1)
        fu, fv = flow_at(xb, yb, 1.0 / t, f, vc, wc)
        vx[q] = fu
        vy[q] = fv
    return depth, vx, vy, obj
