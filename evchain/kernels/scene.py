"""Numba kernels of the driving-scene simulator: exact ray casting against a ground plane and
axis-aligned boxes, procedural textures, camera trajectories and the exact motion field.

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
* ``light [6]``: unit vector towards the sun (3), sun intensity, ambient, sky at the horizon;
  ``light[6]`` sky at the zenith.
* ``traj [10]``: start arc length s, speed m/s, camera height m, pitch amplitude rad, pitch
  frequency Hz, interval between gear shifts s, pitch decay s, first shift s, pitch on (0/1),
  number of segments used.

Camera: X right, Y down, Z forward; a ray through pixel (x, y) has camera direction
((x - cx)/f, (y - cy)/f, 1), so the ray parameter of a hit *is* its depth Z.
All kernels use ``error_model='numpy'`` so that 1/0 gives inf (slab tests rely on it).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_J = dict(cache=True, error_model="numpy")
_I = dict(cache=True, error_model="numpy", inline="always")   # helpers of the hot loops

INF = np.inf

# Width of a sample's box filter on the box faces' textures, in sample spacings. 1 would be the
# sample's own share of the pixel; a GPU's mip-mapped bilinear lookup (TORCS, the thesis's
# renderer) averages over texels of 1-2 footprints blended with a tent of one texel, a filter as
# wide as a box of sqrt(3) to 2 sqrt(3) footprints (equal variance); 2 is at its narrow end.
# The ground's mip levels have texels of 1-2 footprints.
TEXTURE_FOOTPRINT = 2.0

# Window grids, in fractions of a floor (z) and of a window column (u): the band of windows
# zlo..zhi, the window ulo..uhi of each column and its albedo w0 + w1 * (hash in [0, 1)).
GREY_GRID = (0.3, 0.85, 0.2, 0.8, 0.06, 0.2)        # material 1
ORANGE_GRID = (0.15, 0.9, 0.3, 0.7, 0.1, 0.15)      # materials 2 and 3


# ----------------------------------------------------------------------------- hashing / noise

@njit(**_I)
def hash3(i, j, s):
    """Integer hash of three ints to a float in [0, 1) (32-bit mixing, no overflow)."""
    h = ((i * 374761393) ^ (j * 668265263) ^ (s * 1442695041)) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / 16777216.0


# ----------------------------------------------------------------------------- road geometry

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
    the car's x (thesis eq. 3.4), pitched about its own centre."""
    speed = traj[1]
    s = traj[0] + speed * t
    px, py, psi, kap = path_pose(s, segs)
    th, dth = pitch_angle(t, traj)
    dpsi = speed * kap
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


# ----------------------------------------------------------------------------- tracing

@njit(**_I)
def trace(ox, oy, oz, dx, dy, dz, boxes, cand, start, stop, cand_minz):
    """Nearest hit of the ray o + t d (t > 0) among the ground plane z = 0 and the boxes
    cand[start:stop] (sorted by their lower depth bound cand_minz, which allows early exit).

    Returns (t, kind, index, face): kind 0 sky, 1 ground, 2 box; face = 2 * axis + (1 if the
    max side of the slab)."""
    tb = INF
    kind = 0
    idx = -1
    face = -1
    if dz < 0.0 and oz > 0.0:
        tb = -oz / dz
        kind = 1
    if stop <= start:
        return tb, kind, idx, face
    ix = 1.0 / dx
    iy = 1.0 / dy
    iz = 1.0 / dz
    for c in range(start, stop):
        if cand_minz[c] >= tb:
            break
        b = cand[c]
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


# ----------------------------------------------------------------------------- textures

@njit(**_J)
def ground_levels(fp, tex_inv, tex_off, lv_inv, lv_off, lv_mask):
    """Mip level of each ground texture for a sample footprint fp (m): the finest level whose
    texels are at least fp wide. Writes its inverse texel size, offset and index mask."""
    nlev = tex_off.shape[1]
    for q in range(tex_inv.shape[0]):
        lv = 0
        texel = 1.0 / tex_inv[q]
        while lv < nlev - 1 and texel < fp:
            lv += 1
            texel *= 2.0
        lv_inv[q] = tex_inv[q] * 0.5 ** lv
        lv_off[q] = tex_off[q, lv]
        lv_mask[q] = (np.int64(1) << (nlev - 1 - lv)) - 1


@njit(**_I)
def orange_wall(p0, z):
    """Albedo of the orange wall at height z: p0 with a darker band every 0.6 m."""
    return p0 * 0.75 if z - 0.6 * math.floor(z / 0.6) < 0.06 else p0


@njit(**_I)
def periodic_cover(a, b, lo, hi):
    """Length of [a, b] covered by the intervals [m + lo, m + hi], m integer,
    0 <= lo <= hi <= 1."""
    fa = math.floor(a)
    fb = math.floor(b)
    ca = fa * (hi - lo) + min(max(a - fa - lo, 0.0), hi - lo)
    cb = fb * (hi - lo) + min(max(b - fb - lo, 0.0), hi - lo)
    return cb - ca


@njit(**_J)
def box_albedo(mat, p0, p1, p2, p3, bid, u, z, wu):
    """Albedo of a box face at face-horizontal coordinate u and height z (materials:
    0 plain, 1 grey window grid, 2 orange facade, 3 orange with extra vertical lines, 4 car),
    averaged over [u - wu / 2, u + wu / 2] (exactly: the grids are piecewise constant along u;
    wu = 0: the value at u; wu at most 64 window columns). The average is the texture
    prefilter of a sample whose footprint on the face is wu wide along u: at grazing angles a
    sample spans several window columns, whose point samples would alternate between window
    and wall from frame to frame."""
    if mat == 0:
        return p0
    if mat == 4:    # car: dark window band between p1 and p2
        if z > p1 and z < p2:
            return 0.05
        if z < p3:
            return 0.08
        return p0
    fh = p1
    cw = p2
    fi = math.floor(z / fh)
    fz = z / fh - fi
    if mat == 1:
        zlo, zhi, ulo, uhi, w0, w1 = GREY_GRID
        wall = p0 + 0.06 * (hash3(np.int64(fi), bid, 77) - 0.5)
    else:
        zlo, zhi, ulo, uhi, w0, w1 = ORANGE_GRID
        wall = orange_wall(p0, z)
    lines = mat == 3          # vertical lines 0.12 m wide every metre, over everything else
    band = fz > zlo and fz < zhi
    if not wu > 1e-9 * cw:     # a point sample (also below rounding)
        if lines and u - math.floor(u) < 0.12:
            return 0.15
        ci = math.floor(u / cw)
        fu = u / cw - ci
        if band and fu > ulo and fu < uhi:
            return w0 + w1 * hash3(np.int64(ci), np.int64(fi), bid)
        return wall
    wu = min(wu, 64.0 * cw)      # an edge-on face: the 64 window columns around u
    u0 = u - 0.5 * wu
    u1 = u + 0.5 * wu
    on_lines = periodic_cover(u0, u1, 0.0, 0.12) if lines else 0.0
    acc = 0.15 * on_lines
    rest = wu - on_lines       # length on the wall, less the windows below
    if band:
        s0 = u0 / cw
        s1 = u1 / cw
        c0 = math.floor(s0)
        c1 = math.floor(s1)
        for ci in range(np.int64(c0), np.int64(c1) + 1):
            a = max(s0, ci + ulo) * cw
            b = min(s1, ci + uhi) * cw
            if b > a:
                ln = b - a
                if lines:
                    ln -= periodic_cover(a, b, 0.0, 0.12)
                acc += ln * (w0 + w1 * hash3(np.int64(ci), np.int64(fi), bid))
                rest -= ln
    return (acc + rest * wall) / wu


@njit(**_I)
def flow_at(xb, yb, rho, f, vc, wc):
    """Motion field (px/s) at normalised coordinates (xb, yb) with inverse depth rho."""
    u = (-vc[0] + xb * vc[2]) * rho + wc[0] * xb * yb - wc[1] * (1.0 + xb * xb) + wc[2] * yb
    v = (-vc[1] + yb * vc[2]) * rho + wc[0] * (1.0 + yb * yb) - wc[1] * xb * yb - wc[2] * xb
    return f * u, f * v


# ----------------------------------------------------------------------------- per-frame culling

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


# ----------------------------------------------------------------------------- render

@njit(**_J)
def ground_pass(kd, dxs, dys, tg, ox, oy, pcol, segs, ground, light, tex, lv_inv, lv_off,
                lv_mask, acc):
    """acc[pcol[c]] += ground intensity at world (ox + tg dxs[c], oy + tg dys[c]) for every
    sample c of a row with kd[c] == 1 (texture levels given).

    The albedo of the ground at world (x, y): asphalt with noise, centre and edge lines,
    sidewalk slabs and kerb, grass or paving beyond, the noise from the mip levels chosen by
    :func:`ground_levels` for the sample footprint. Written out with the parameters in scalars
    (an inlined helper taking arrays costs reference counting per sample)."""
    lam = light[2]
    if lam < 0.0:
        lam = 0.0
    lit = light[4] + light[3] * lam
    off = ground[0]
    hw = ground[1]
    lw = ground[2] * 0.5
    edge = ground[3]
    sw = ground[4]
    dash = ground[5]
    per = ground[6]
    seed3 = np.int64(ground[8]) + 3
    tb_ = 1 if ground[7] == 0.0 else 2
    base_b = 0.1 if ground[7] == 0.0 else 0.3
    ia = lv_inv[0]
    oa = lv_off[0]
    ma = lv_mask[0]
    ib = lv_inv[tb_]
    ob = lv_off[tb_]
    mb = lv_mask[tb_]
    straight = segs.shape[0] == 1 and segs[0, 4] == 0.0
    x0 = segs[0, 0]
    y0 = segs[0, 1]
    ch = segs[0, 8]
    sh = segs[0, 9]
    s0 = segs[0, 5]
    sl = 1.2
    for c in range(kd.shape[0]):
        if kd[c] != 1:
            continue
        x = ox + tg * dxs[c]
        y = oy + tg * dys[c]
        if straight:
            s = s0 + ((x - x0) * ch + (y - y0) * sh)
            d = -(x - x0) * sh + (y - y0) * ch
        else:
            s, d = road_coords_nrc(x, y, segs)
        w = abs(d - off)
        if w < hw:
            a = -1.0
            if w < lw:
                if s - per * math.floor(s / per) < dash:
                    a = 0.75
            if abs(w - edge) < lw:
                a = 0.75
            if a < 0.0:
                i = np.int64(math.floor(x * ia)) & ma
                j = np.int64(math.floor(y * ia)) & ma
                a = 0.16 + tex[oa + j * (ma + 1) + i]
        elif w < hw + sw:
            if w < hw + 0.3:
                a = 0.45
            else:
                u = s - sl * math.floor(s / sl)
                v = (w - hw) - sl * math.floor((w - hw) / sl)
                if u < 0.05 or v < 0.05:
                    a = 0.2
                else:
                    a = 0.36 + 0.1 * (hash3(np.int64(math.floor(s / sl)),
                                            np.int64(math.floor((w - hw) / sl)), seed3) - 0.5)
        else:
            i = np.int64(math.floor(x * ib)) & mb
            j = np.int64(math.floor(y * ib)) & mb
            a = base_b + tex[ob + j * (mb + 1) + i]
        acc[pcol[c]] += a * lit


@njit(**_J)
def face_light(light):
    """Lambert factor ambient + sun * max(0, n.s) of the six box faces (2 * axis + max side)."""
    lit = np.empty(6)
    for face in range(6):
        lam = (1.0 if (face % 2) == 1 else -1.0) * light[face // 2]
        if lam < 0.0:
            lam = 0.0
        lit[face] = light[4] + light[3] * lam
    return lit


@njit(**_J)
def box_pass(kd, tb, hid, fc, dxs, dys, gxs, gys, ox, oy, oz, dz, pcol, box_mat, box_par, lit,
             acc):
    """acc[pcol[c]] += intensity of the box hit by sample c of a row, for every c with
    kd[c] == 2 (box hid[c], face fc[c], ray parameter tb[c], direction (dxs, dys, dz)[c]).

    Side faces are textured by :func:`box_albedo` over the sample's footprint along u times
    :data:`TEXTURE_FOOTPRINT`, t gxs[c] on a face of constant world y (u = world x), t gys[c] on
    one of constant x: per sample spacing fscale of normalised image x (image x axis (xh0, xh1)
    in the world) u moves by t fscale |xh0 - dx xh1 / dy| and t fscale |xh1 - dy xh0 / dx|.

    Window grids (materials 1 and 2) are :func:`box_albedo` written out, with values kept
    while neighbouring samples stay on the same box (inverse column width and floor height,
    the material's grid), floor (wall albedo) and window column (window albedo)."""
    pb = -1          # box, floor and column of the cached values
    pf = 0.0
    pc = 0.0
    win = 0.0
    wall = 0.0
    wall0 = 0.0
    icw = 1.0
    ifh = 1.0
    zlo, zhi, ulo, uhi, w0, w1 = GREY_GRID
    for c in range(kd.shape[0]):
        if kd[c] != 2:
            continue
        t = tb[c]
        face = fc[c]
        idx = hid[c]
        if face >= 4:
            a = 0.8 * box_par[idx, 0]
        else:
            mat = box_mat[idx]
            if mat == 1 or mat == 2:
                if idx != pb:
                    icw = 1.0 / box_par[idx, 2]
                    ifh = 1.0 / box_par[idx, 1]
                    if mat == 1:
                        zlo, zhi, ulo, uhi, w0, w1 = GREY_GRID
                    else:
                        zlo, zhi, ulo, uhi, w0, w1 = ORANGE_GRID
                    pb = idx
                    pf = -1.5      # no floor: the hashes are stale
                z = oz + t * dz
                zf = z * ifh
                fi = math.floor(zf)
                fz = zf - fi
                if fi != pf:
                    wall0 = box_par[idx, 0] + 0.06 * (hash3(np.int64(fi), idx, 77) - 0.5)
                    pf = fi
                    pc = -1.5
                wall = wall0
                if mat == 2:
                    wall = orange_wall(box_par[idx, 0], z)
                a = wall
                if (fz > zlo) & (fz < zhi):
                    if face < 2:
                        su = (oy + t * dys[c]) * icw
                        wn = t * gys[c] * icw
                    else:
                        su = (ox + t * dxs[c]) * icw
                        wn = t * gxs[c] * icw
                    s0 = su - 0.5 * wn          # footprint [s0, s1] in window columns
                    s1 = s0 + wn
                    c0 = math.floor(s0)
                    if s1 <= c0 + 1.0 + ulo:    # no window but column c0's: its share
                        ov = min(s1, c0 + uhi) - max(s0, c0 + ulo)
                        if ov >= 0.0:           # it touches the window
                            if c0 != pc:
                                win = w0 + w1 * hash3(np.int64(c0), np.int64(fi), idx)
                                pc = c0
                            if (s0 >= c0 + ulo) & (s1 <= c0 + uhi):
                                a = win         # within it (also a point sample: wn 0)
                            else:               # across an edge: then s1 > s0
                                a = wall + (win - wall) * (ov / wn)
                    else:                       # the windows of columns c0 to c1
                        if wn > 64.0:           # at most 64 columns
                            wn = 64.0
                            s0 = su - 0.5 * wn
                            s1 = s0 + wn
                            c0 = math.floor(s0)
                        c1 = math.floor(s1 - ulo)
                        sw = 0.0
                        so = 0.0
                        for ci in range(np.int64(c0), np.int64(c1) + 1):
                            ov = max(min(s1, ci + uhi) - max(s0, ci + ulo), 0.0)
                            sw += ov * hash3(ci, np.int64(fi), idx)
                            so += ov
                        a = wall + ((w0 - wall) * so + w1 * sw) / wn
            elif mat == 0:
                a = box_par[idx, 0]
            else:
                if face < 2:
                    u = oy + t * dys[c]
                    wu = t * gys[c]
                else:
                    u = ox + t * dxs[c]
                    wu = t * gxs[c]
                a = box_albedo(mat, box_par[idx, 0], box_par[idx, 1], box_par[idx, 2],
                               box_par[idx, 3], idx, u, oz + t * dz, wu)
        acc[pcol[c]] += a * lit[face]

@njit(**_J)
def flow_terms(xbs, vc, wc):
    """Per-column terms of the motion field for the sample columns xbs (one frame): rows
    -v0 + xb v2, w0 xb, w1 (1 + xb^2), w1 xb, w2 xb, as :func:`row_vmax2` uses them."""
    n = xbs.shape[0]
    tm = np.empty((5, n))
    for c in range(n):
        xb = xbs[c]
        tm[0, c] = -vc[0] + xb * vc[2]
        tm[1, c] = wc[0] * xb
        tm[2, c] = wc[1] * (1.0 + xb * xb)
        tm[3, c] = wc[1] * xb
        tm[4, c] = wc[2] * xb
    return tm


@njit(**_J)
def row_vmax2(tm, yb, tb, f, vc, wc, m2):
    """Largest squared motion-field magnitude (px/s)^2 over the samples of a row at yb with
    depths tb[c] (the columns' terms tm from :func:`flow_terms`: the same operations as
    :func:`flow_at`, in its order); m2: scratch [n]. (Two loops, both vectorised.)"""
    a0 = tm[0]
    a1 = tm[1]
    a2 = tm[2]
    a3 = tm[3]
    a4 = tm[4]
    w2y = wc[2] * yb
    dv = -vc[1] + yb * vc[2]
    ev = wc[0] * (1.0 + yb * yb)
    n = tb.shape[0]
    for c in range(n):
        rho = 1.0 / tb[c]
        u = a0[c] * rho + a1[c] * yb - a2[c] + w2y
        v = dv * rho + ev - a3[c] * yb - a4[c]
        q = u * u + v * v
        m2[c] = q if q == q else 0.0      # NaN (a zero depth) is skipped
    # the largest of these non-negative doubles is the largest of their bit patterns as
    # int64: an integer maximum, which compiles to vector code (a float one does not)
    bits = m2.view(np.int64)
    mb = np.int64(0)
    for c in range(n):
        mb = max(mb, bits[c])
    bits[0] = mb           # back to float through the scratch
    return m2[0] * f * f


@njit(**_J)
def row_work(n):
    """Scratch arrays of one sample row of n samples: float64 [8, n], int32 [3, n] (small
    enough to stay in the L1 cache with the rest) and the per-block depth bound of blocks of 16
    samples; the last pair is r0, r1 of the row whose directions the scratch holds (NaN: none)."""
    return (np.empty((8, n)), np.empty((3, n), np.int32), np.empty(n // 16 + 1),
            np.full(2, np.nan))


@njit(**_J)
def level_work(ntex):
    """Per-row texture level scratch: inverse texel sizes, offsets, masks."""
    return np.empty(ntex), np.empty(ntex, np.int64), np.empty(ntex, np.int64)


@njit(**_J)
def render_row(j, pos, rot, vc, wc, f, cx, cy, k, boxes, box_mat, box_par, segs, ground, light,
               lit, tex, tex_inv, tex_off, vis, minz, bbox, xbs, tm, pcol, fw, iw, bmax, rprev,
               lv_inv, lv_off, lv_mask, acc, out):
    """Render image row j into out[j]; return the largest squared image speed of its first
    sample row (the time step's bound on motion: the k sample rows of a pixel row differ by
    less than a pixel).

    Per sample row: the ground hit is one division (no roll: every ray of a row has the same
    world dz); each visible box gets its exact z-slab for the row and the span of sample columns
    it can cover (:func:`box_span`); boxes are visited nearest-first and only the samples of
    their span whose current hit is farther than the box's nearest corner get the exact slab
    test (blocks of 16 samples whose farthest current hit is nearer are skipped whole). The
    result equals testing every box for every sample.

    lit: :func:`face_light`; tm: :func:`flow_terms`; pcol: pixel column of every sample;
    fw, iw, bmax, rprev: scratch (:func:`row_work`, kept between the rows of one frame);
    acc: [W]."""
    w = out.shape[1]
    n = w * k
    inv_k2 = 1.0 / (k * k)
    fscale = 1.0 / (f * k)
    inv_f = 1.0 / f
    ox = pos[0]
    oy = pos[1]
    oz = pos[2]
    vmax2 = 0.0
    nvis = vis.shape[0]
    nblk = (n + 15) // 16
    for i in range(w):
        acc[i] = 0.0
    tb = fw[0]
    dxs = fw[1]
    dys = fw[2]
    ixs = fw[3]
    iys = fw[4]
    m2s = fw[5]
    gxs = fw[6]
    gys = fw[7]
    kd = iw[0]
    hid = iw[1]
    fc = iw[2]
    xh0 = rot[0, 0]
    xh1 = rot[1, 0]
    sky0 = light[5]
    sky1 = light[6]
    for b in range(k):
        yb = (j + (b + 0.5) / k - 0.5 - cy) * inv_f
        r0 = rot[0, 1] * yb + rot[0, 2]
        r1 = rot[1, 1] * yb + rot[1, 2]
        dz = rot[2, 0] * 0.0 + rot[2, 1] * yb + rot[2, 2]   # rot[2, 0] == 0: no roll
        tg = INF
        kind0 = 0
        if dz < 0.0 and oz > 0.0:
            tg = -oz / dz
            kind0 = 1
        for c in range(n):
            tb[c] = tg
            kd[c] = kind0          # hid and fc are read only where kd == 2
        # the horizontal directions depend on the row only through r0, r1, which are the same
        # in every row when the camera does not pitch: recomputed (two divisions per sample)
        # only when r0 or r1 differs from the row before, bit pattern and sign of zero included
        if not (r0 == rprev[0] and r1 == rprev[1]
                and math.copysign(1.0, r0) == math.copysign(1.0, rprev[0])
                and math.copysign(1.0, r1) == math.copysign(1.0, rprev[1])):
            for c in range(n):
                xb = xbs[c]
                dx = xh0 * xb + r0
                dy = xh1 * xb + r1
                dxs[c] = dx
                dys[c] = dy
                ix = 1.0 / dx
                iy = 1.0 / dy
                ixs[c] = ix
                iys[c] = iy
                # texture footprints along u on faces of constant y and x, per unit of t
                gxs[c] = abs(xh0 - dx * xh1 * iy) * fscale * TEXTURE_FOOTPRINT
                gys[c] = abs(xh1 - dy * xh0 * ix) * fscale * TEXTURE_FOOTPRINT
            rprev[0] = r0
            rprev[1] = r1
        for q in range(nblk):
            bmax[q] = tg
        iz = 1.0 / dz
        for q in range(nvis):
            bq = vis[q]
            mz = minz[bq]
            if mz >= tg:
                break
            # outside the projection's bounding rectangle (with a relative margin): no hit
            if yb < bbox[bq, 2] - 1e-9 * (1.0 + abs(bbox[bq, 2])) or \
                    yb > bbox[bq, 3] + 1e-9 * (1.0 + abs(bbox[bq, 3])):
                continue
            t1 = (boxes[bq, 2] - oz) * iz
            t2 = (boxes[bq, 5] - oz) * iz
            tzn = min(t1, t2)
            tzf = max(t1, t2)
            if tzf <= 0.0 or tzn >= tg:
                continue
            ta = max(tzn, mz, 1e-9)
            tz = min(tzf, tg)
            if tzn != tzn or tzf != tzf:
                ta = 1e-9
                tz = tg
            c0, c1 = box_span(boxes[bq, 0], boxes[bq, 1], boxes[bq, 3], boxes[bq, 4], ox, oy,
                              xh0, xh1, r0, r1, ta * (1.0 - 1e-9), tz * (1.0 + 1e-9), f, cx,
                              k, n)
            bx0 = bbox[bq, 0] * f + cx
            bx1 = bbox[bq, 1] * f + cx
            if bx0 > -1e6:
                c0 = max(c0, int(math.floor((bx0 + 0.5) * k - 0.5)) - 2)
            if bx1 < 1e6:
                c1 = min(c1, int(math.ceil((bx1 + 0.5) * k - 0.5)) + 2)
            ex0 = boxes[bq, 0] - ox
            ex1 = boxes[bq, 3] - ox
            ey0 = boxes[bq, 1] - oy
            ey1 = boxes[bq, 4] - oy
            for blk in range(c0 >> 4, (c1 >> 4) + 1 if c1 >= c0 else c0 >> 4):
                if mz >= bmax[blk]:
                    continue
                lo = max(c0, blk << 4)
                hi = min(c1 + 1, (blk + 1) << 4)
                hit = False
                for c in range(lo, hi):
                    if mz >= tb[c]:
                        continue
                    ix = ixs[c]
                    iy = iys[c]
                    u1 = ex0 * ix
                    u2 = ex1 * ix
                    txn = min(u1, u2)
                    txf = max(u1, u2)
                    u1 = ey0 * iy
                    u2 = ey1 * iy
                    tyn = min(u1, u2)
                    tyf = max(u1, u2)
                    tn = max(txn, max(tyn, tzn))
                    tf = min(txf, min(tyf, tzf))
                    if tn <= tf and tn > 0.0 and tn < tb[c]:
                        tb[c] = tn
                        kd[c] = 2
                        hid[c] = bq
                        hit = True
                        if txn >= tyn and txn >= tzn:
                            fc[c] = 0 if dxs[c] > 0 else 1
                        elif tyn >= tzn:
                            fc[c] = 2 if dys[c] > 0 else 3
                        else:
                            fc[c] = 4 if dz > 0 else 5
                if hit:
                    m = 0.0
                    for c in range(blk << 4, min(n, (blk + 1) << 4)):
                        if tb[c] > m:
                            m = tb[c]
                    bmax[blk] = m
        if b == 0:    # the speed bound of the time step: one sample row per pixel row is enough
            m2 = row_vmax2(tm, yb, tb, f, vc, wc, m2s)
            if m2 > vmax2:
                vmax2 = m2
        # shading in separate simple passes over the row (one huge inlined loop body compiles
        # to slower code): sky here, ground and box samples by their own kernels
        if kind0 == 1:      # texture levels for the row's largest ground footprint
            d2 = max(dxs[0] ** 2 + dys[0] ** 2, dxs[n - 1] ** 2 + dys[n - 1] ** 2) + dz * dz
            ground_levels(tg * fscale * d2 / (-dz), tex_inv, tex_off, lv_inv, lv_off, lv_mask)
        for c in range(n):
            if kd[c] == 0:
                ddx = dxs[c]
                ddy = dys[c]
                e = dz / math.sqrt(ddx * ddx + ddy * ddy + dz * dz)
                if e < 0.0:
                    e = 0.0
                acc[pcol[c]] += sky0 + (sky1 - sky0) * e
        ground_pass(kd, dxs, dys, tg, ox, oy, pcol, segs, ground, light, tex, lv_inv, lv_off,
                    lv_mask, acc)
        box_pass(kd, tb, hid, fc, dxs, dys, gxs, gys, ox, oy, oz, dz, pcol, box_mat, box_par,
                 lit, acc)
    for i in range(w):
        out[j, i] = acc[i] * inv_k2
    return vmax2


@njit(**_J)
def sample_columns(w, k, cx, f):
    """Normalised x of every sample column."""
    xbs = np.empty(w * k)
    for i in range(w):
        for a in range(k):
            xbs[i * k + a] = (i + (a + 0.5) / k - 0.5 - cx) / f
    return xbs


@njit(**_J)
def pixel_columns(w, k):
    """Pixel column of every sample column."""
    pcol = np.empty(w * k, np.int64)
    for c in range(w * k):
        pcol[c] = c // k
    return pcol


@njit(cache=True, error_model="numpy", nogil=True)
def render_rows(pos, rot, vc, wc, f, cx, cy, k, boxes, box_mat, box_par, segs, ground, light,
                tex, tex_inv, tex_off, vis, minz, bbox, out, j0, jstep):
    """:func:`render` of the rows j0, j0 + jstep, ... only (the maximum speed over their
    samples): threads render interleaved rows of one frame (same result)."""
    w = out.shape[1]
    xbs = sample_columns(w, k, cx, f)
    tm = flow_terms(xbs, vc, wc)
    pcol = pixel_columns(w, k)
    fw, iw, bmax, rprev = row_work(w * k)
    lv_inv, lv_off, lv_mask = level_work(tex_inv.shape[0])
    acc = np.empty(w)
    lit = face_light(light)
    vmax2 = 0.0
    for j in range(j0, out.shape[0], jstep):
        m2 = render_row(j, pos, rot, vc, wc, f, cx, cy, k, boxes, box_mat, box_par, segs,
                        ground, light, lit, tex, tex_inv, tex_off, vis, minz, bbox, xbs, tm, pcol,
                        fw, iw, bmax, rprev, lv_inv, lv_off, lv_mask, acc, out)
        if m2 > vmax2:
            vmax2 = m2
    return math.sqrt(vmax2)


@njit(cache=True, error_model="numpy", nogil=True)
def render(pos, rot, vc, wc, f, cx, cy, k, boxes, box_mat, box_par, segs, ground, light,
           tex, tex_inv, tex_off, vis, minz, bbox, out):
    """Render one frame into out [H, W] (float32, linear intensity, k x k supersampling
    averaged) and return the maximum motion-field magnitude (px/s) over the samples of every
    pixel row's first sample row.
    vis: visible boxes nearest first, minz their depth bounds (:func:`frame_boxes`)."""
    return render_rows(pos, rot, vc, wc, f, cx, cy, k, boxes, box_mat, box_par, segs, ground,
                       light, tex, tex_inv, tex_off, vis, minz, bbox, out, 0, 1)


# ----------------------------------------------------------------------------- ground truth

@njit(**_J)
def truth_query(x, y, t_s, f, cx, cy, boxes, segs, traj, depth, vx, vy, obj):
    """Exact depth (m, inf for sky), motion field (px/s) and object id (int64: the index of the
    box seen, -2 for the ground, -1 for the sky: ``OBJECT_*`` in :mod:`evchain.sim.world`) at
    pixel positions (x, y) and times t_s (seconds), one query per element. Uses the same
    tracing as the renderer."""
    n = x.shape[0]
    nb = boxes.shape[0]
    cand = np.arange(nb)
    minz = np.full(nb, -INF)
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
        t, kind, idx, face = trace(pos[0], pos[1], pos[2], dx, dy, dz, boxes, cand, 0, nb, minz)
        depth[q] = t
        obj[q] = idx if kind == 2 else (-2 if kind == 1 else -1)
        fu, fv = flow_at(xb, yb, 1.0 / t, f, vc, wc)
        vx[q] = fu
        vy[q] = fv


@njit(**_J)
def camera_states(t_s, segs, traj, pos, rot, vc, wc):
    """camera_state for many times: pos [n, 3], rot [n, 3, 3], vc [n, 3], wc [n, 3]."""
    for q in range(t_s.shape[0]):
        camera_state(t_s[q], segs, traj, pos[q], rot[q], vc[q], wc[q])
