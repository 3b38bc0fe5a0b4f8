"""Numba kernels of the scene renderer's shading: procedural textures (hashed noise, mip-mapped
ground textures, window grids of the facades averaged over a sample's footprint), Lambert light
and the per-row shading passes of ground and box samples. Array layouts:
:mod:`evchain.kernels.scene_geometry`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from evchain.kernels.scene_geometry import road_coords_nrc

_J = dict(cache=True, error_model="numpy")
_I = dict(cache=True, error_model="numpy", inline="always")   # helpers of the hot loops
# kernels called per row with array arguments: compiled without reference counting (numba's
# counts on every array argument, atomic operations that its pruning pass keeps where they
# straddle branches; docs/explanation/scene.md, "Rendering"); they allocate nothing
_R = dict(cache=True, error_model="numpy", _nrt=False)
# Floors used as floats are np.floor: numba's math.floor returns an int, and the conversions
# to int and back on every sample are measurable (same values below 2^53).

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


@njit(**_I)
def hash3(i, j, s):
    """Integer hash of three ints to a float in [0, 1) (32-bit mixing, no overflow)."""
    h = ((i * 374761393) ^ (j * 668265263) ^ (s * 1442695041)) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / 16777216.0


@njit(**_R)
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
    return p0 * 0.75 if z - 0.6 * np.floor(z / 0.6) < 0.06 else p0


@njit(**_I)
def periodic_cover(a, b, lo, hi):
    """Length of [a, b] covered by the intervals [m + lo, m + hi], m integer,
    0 <= lo <= hi <= 1."""
    fa = math.floor(a)
    fb = math.floor(b)
    ca = fa * (hi - lo) + min(max(a - fa - lo, 0.0), hi - lo)
    cb = fb * (hi - lo) + min(max(b - fb - lo, 0.0), hi - lo)
    return cb - ca


@njit(**_R)
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


@njit(**_R)
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
                if s - per * np.floor(s / per) < dash:
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
                u = s - sl * np.floor(s / sl)
                v = (w - hw) - sl * np.floor((w - hw) / sl)
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


@njit(**_R)
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
                fi = np.floor(zf)
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
                    c0 = np.floor(s0)
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
                            c0 = np.floor(s0)
                        c1 = np.floor(s1 - ulo)
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
