"""Numba kernels of the driving-scene simulator: road coordinates, the camera's trajectory and
pose, and the exact motion field. The other ``scene_*`` kernel modules build on these:
:mod:`~evchain.kernels.scene_culling` (boxes a frame may see),
:mod:`~evchain.kernels.scene_shading` (textures and light), :mod:`~evchain.kernels.scene_render`
(the row renderer) and :mod:`~evchain.kernels.scene_truth` (exact depth, flow and object ids).

Array layouts (all float64 unless said otherwise; built by :mod:`evchain.sim.world`):

* ``boxes [N, 6]``: xmin, ymin, zmin, xmax, ymax, zmax (world metres; z up, ground at z = 0).
* ``box_mat [N]`` int64: material id (see ``MAT_*`` in :mod:`evchain.sim.world`);
  ``box_par [N, 4]``: material parameters.
* ``segs [M, 11]``: the driving line as segments x0, y0, heading0, length, kappa (signed
  curvature, left > 0, 0 = straight), s0 (arc length at the start), xc, yc (arc centre),
  cos(heading0), sin(heading0), polar angle of (x0, y0) about the arc centre.
* ``ground [9]``: road centre offset from the driving line (left > 0), asphalt half width,
  line width, edge-line offset, sidewalk width, dash length, dash period, kind beyond the
  sidewalk (0 grass, 1 paving), texture seed.
* ``light [7]``: unit vector towards the sun (3), sun intensity, ambient, sky at the horizon,
  sky at the zenith.
* ``tex`` float32, ``tex_inv [3]``, ``tex_off [3, levels]`` int64: the mip-mapped ground
  textures (:func:`evchain.sim.world.ground_textures`).
* ``traj [13]``: start arc length s, speed m/s, camera height m, pitch amplitude rad, pitch
  frequency Hz, interval between gear shifts s, pitch decay s, first shift s, pitch on (0/1),
  number of segments used, pan rate rad/s (to the right), tilt rate rad/s (up), time s from
  which the camera pans and tilts.

The renderer reads them as one record, :class:`WorldArrays`, and each frame's camera and
visible boxes as another, :class:`FrameView` (named tuples: numba passes them like their fields).

Camera: X right, Y down, Z forward; a ray through pixel (x, y) has camera direction
((x - cx)/f, (y - cy)/f, 1), so the ray parameter of a hit *is* its depth Z.
All kernels use ``error_model='numpy'`` so that 1/0 gives inf (slab tests rely on it).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

_J = dict(cache=True, error_model="numpy")
_I = dict(cache=True, error_model="numpy", inline="always")   # helpers of the hot loops

INF = np.inf


class WorldArrays(NamedTuple):
    """The world as the kernels read it (layouts above); built from a scene's arrays."""

    boxes: np.ndarray       #: float64 [N, 6], metres
    box_mat: np.ndarray     #: int64 [N], material id
    box_par: np.ndarray     #: float64 [N, 4], material parameters
    segs: np.ndarray        #: float64 [M, 11], the driving line
    ground: np.ndarray      #: float64 [9], road and ground parameters
    light: np.ndarray       #: float64 [7], sun and sky
    tex: np.ndarray         #: float32 [texels], the ground textures' mip levels
    tex_inv: np.ndarray     #: float64 [3], inverse texel size of each texture's level 0, 1/m
    tex_off: np.ndarray     #: int64 [3, levels], offset of each level in ``tex``


class FrameView(NamedTuple):
    """One frame's camera (:func:`camera_state` at the frame's time, the intrinsics and the
    supersampling) and the boxes it may see (:func:`~evchain.kernels.scene_culling.frame_boxes`).
    """

    pos: np.ndarray     #: float64 [3], camera position, world metres
    rot: np.ndarray     #: float64 [3, 3], camera-to-world rotation (columns: camera axes)
    vc: np.ndarray      #: float64 [3], linear velocity in camera coordinates, m/s
    wc: np.ndarray      #: float64 [3], angular velocity in camera coordinates, rad/s
    f: float            #: focal length, px
    cx: float           #: principal point x, px
    cy: float           #: principal point y, px
    k: int              #: samples per pixel along x and along y
    vis: np.ndarray     #: int64 [nvis], the visible boxes, nearest first
    minz: np.ndarray    #: float64 [N], lower depth bound of each visible box, m
    bbox: np.ndarray    #: float64 [N, 4], its projection's bounding rectangle x0, x1, y0, y1
    #                      in normalised image coordinates


@njit(**_I)
def road_coords(x, y, segs):
    """Arc length s along the driving line and signed lateral offset d (left > 0) of (x, y).

    The segment whose extent contains the point and whose |d| is smallest wins; the first and
    last straight segments extend to infinity."""
    m = segs.shape[0]
    if m == 1 and segs[0, 4] == 0.0:       # one straight line (all scenarios but curves)
        x0 = segs[0, 0]
        y0 = segs[0, 1]
        c = segs[0, 8]
        sn = segs[0, 9]
        return (segs[0, 5] + ((x - x0) * c + (y - y0) * sn)), -(x - x0) * sn + (y - y0) * c
    best_s = 0.0
    best_d = INF
    for k in range(m):
        x0 = segs[k, 0]
        y0 = segs[k, 1]
        ln = segs[k, 3]
        kap = segs[k, 4]
        s0 = segs[k, 5]
        if kap == 0.0:
            c = segs[k, 8]
            sn = segs[k, 9]
            sl = (x - x0) * c + (y - y0) * sn
            dl = -(x - x0) * sn + (y - y0) * c
        else:
            xc = segs[k, 6]
            yc = segs[k, 7]
            rx = x - xc
            ry = y - yc
            rho = math.sqrt(rx * rx + ry * ry)
            dphi = math.atan2(ry, rx) - segs[k, 10] - kap * ln * 0.5
            dphi = dphi - 2.0 * math.pi * math.floor((dphi + math.pi) / (2.0 * math.pi))
            sl = dphi / kap + ln * 0.5
            dl = 1.0 / kap - (rho if kap > 0 else -rho)
        lo = -INF if (k == 0 and kap == 0.0) else 0.0
        hi = INF if (k == m - 1 and kap == 0.0) else ln
        if sl >= lo and sl <= hi and abs(dl) < abs(best_d):
            best_d = dl
            best_s = s0 + sl
    return best_s, best_d


@njit(**_J)
def road_coords_nrc(x, y, segs):
    """:func:`road_coords` as a plain (not inlined) call."""
    return road_coords(x, y, segs)


@njit(**_J)
def path_pose(s, segs):
    """Position (x, y), heading and signed curvature of the driving line at arc length s."""
    m = segs.shape[0]
    k = 0
    while k < m - 1 and s >= segs[k + 1, 5]:
        k += 1
    x0 = segs[k, 0]
    y0 = segs[k, 1]
    h0 = segs[k, 2]
    kap = segs[k, 4]
    u = s - segs[k, 5]
    if kap == 0.0:
        return x0 + u * math.cos(h0), y0 + u * math.sin(h0), h0, 0.0
    h = h0 + kap * u
    return (x0 + (math.sin(h) - math.sin(h0)) / kap,
            y0 - (math.cos(h) - math.cos(h0)) / kap, h, kap)


@njit(**_J)
def pitch_angle(t, traj):
    """Pitch (rad, nose up > 0) and its rate (rad/s): damped oscillations after gear shifts."""
    if traj[8] == 0.0:
        return 0.0, 0.0
    amp = traj[3]
    om = 2.0 * math.pi * traj[4]
    interval = traj[5]
    decay = traj[6]
    first = traj[7]
    th = 0.0
    dth = 0.0
    if t < first:
        return 0.0, 0.0
    kmax = int(math.floor((t - first) / interval))
    kmin = max(0, kmax - int(math.ceil(12.0 * decay / interval)) - 1)
    for k in range(kmin, kmax + 1):
        u = t - (first + k * interval)
        if u < 0.0:
            continue
        e = math.exp(-u / decay)
        th += amp * e * math.sin(om * u)
        dth += amp * e * (om * math.cos(om * u) - math.sin(om * u) / decay)
    return th, dth


@njit(**_J)
def camera_state(t, segs, traj, pos, rot, vc, wc):
    """Camera pose and velocities at time t (s).

    Writes pos (world, 3), rot (camera-to-world rotation, 3x3: columns are the camera axes in
    world coordinates), vc and wc: linear and angular velocity of the camera in camera
    coordinates. The camera rides at height traj[2] above the driving line, optical axis along
    the car's x (thesis eq. 3.4), pitched about its own centre, turned by the pan and tilt
    rates from traj[12] on."""
    speed = traj[1]
    s = traj[0] + speed * t
    px, py, psi, kap = path_pose(s, segs)
    th, dth = pitch_angle(t, traj)
    dpsi = speed * kap
    if (traj[10] != 0.0 or traj[11] != 0.0) and t >= traj[12]:
        # panning (to the right: the heading decreases) and tilting (nose up)
        psi -= traj[10] * (t - traj[12])
        dpsi -= traj[10]
        th += traj[11] * (t - traj[12])
        dth += traj[11]
    cp = math.cos(psi)
    sp = math.sin(psi)
    ct = math.cos(th)
    st = math.sin(th)
    # vehicle axes in world: x_v = (cp ct, sp ct, st) (nose up for th > 0),
    # y_v = (-sp, cp, 0), z_v = x_v cross y_v
    xv0 = cp * ct
    xv1 = sp * ct
    xv2 = st
    yv0 = -sp
    yv1 = cp
    yv2 = 0.0
    zv0 = xv1 * yv2 - xv2 * yv1
    zv1 = xv2 * yv0 - xv0 * yv2
    zv2 = xv0 * yv1 - xv1 * yv0
    # camera X = -y_v, Y = -z_v, Z = x_v
    rot[0, 0] = -yv0
    rot[1, 0] = -yv1
    rot[2, 0] = -yv2
    rot[0, 1] = -zv0
    rot[1, 1] = -zv1
    rot[2, 1] = -zv2
    rot[0, 2] = xv0
    rot[1, 2] = xv1
    rot[2, 2] = xv2
    pos[0] = px
    pos[1] = py
    pos[2] = traj[2]
    vw0 = speed * cp
    vw1 = speed * sp
    # angular velocity in world: dpsi z + dth * (-y_v) (nose up about -y_v)
    ww0 = -dth * yv0
    ww1 = -dth * yv1
    ww2 = dpsi
    for a in range(3):
        vc[a] = rot[0, a] * vw0 + rot[1, a] * vw1
        wc[a] = rot[0, a] * ww0 + rot[1, a] * ww1 + rot[2, a] * ww2


@njit(**_J)
def camera_states(t_s, segs, traj, pos, rot, vc, wc):
    """camera_state for many times: pos [n, 3], rot [n, 3, 3], vc [n, 3], wc [n, 3]."""
    for q in range(t_s.shape[0]):
        camera_state(t_s[q], segs, traj, pos[q], rot[q], vc[q], wc[q])


@njit(**_I)
def flow_at(xb, yb, rho, f, vc, wc):
    """Motion field (px/s) at normalised coordinates (xb, yb) with inverse depth rho."""
    u = (-vc[0] + xb * vc[2]) * rho + wc[0] * xb * yb - wc[1] * (1.0 + xb * xb) + wc[2] * yb
    v = (-vc[1] + yb * vc[2]) * rho + wc[0] * (1.0 + yb * yb) - wc[1] * xb * yb - wc[2] * xb
    return f * u, f * v
