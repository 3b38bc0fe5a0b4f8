"""Slow, obvious numpy references for the scene kernels, evchain.kernels.scene_* (vectorised
over rays, no culling).

Camera pose from explicit rotation matrices, tracing by testing every box for every ray,
textures written as numpy ``where`` chains, flow by finite differences of the projection.
"""

from __future__ import annotations

import math

import numpy as np

from evchain.kernels.scene_shading import TEXTURE_FOOTPRINT

M32 = 0xFFFFFFFF


def hash3(i, j, s):
    i, j, s = (np.asarray(v, np.int64) for v in (i, j, s))
    h = ((i * 374761393) ^ (j * 668265263) ^ (s * 1442695041)) & M32
    h = ((h ^ (h >> 13)) * 1274126177) & M32
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / 16777216.0


def road_coords(x, y, segs):
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    best_s = np.zeros(x.shape)
    best_d = np.full(x.shape, np.inf)
    m = len(segs)
    for k, (x0, y0, h0, ln, kap, s0, xc, yc, *_rest) in enumerate(segs):
        if kap == 0:
            sl = (x - x0) * np.cos(h0) + (y - y0) * np.sin(h0)
            dl = -(x - x0) * np.sin(h0) + (y - y0) * np.cos(h0)
        else:
            rho = np.hypot(x - xc, y - yc)
            phi0 = np.arctan2(y0 - yc, x0 - xc)
            dphi = np.arctan2(y - yc, x - xc) - phi0 - kap * ln / 2
            dphi = (dphi + np.pi) % (2 * np.pi) - np.pi
            sl = dphi / kap + ln / 2
            dl = 1 / kap - np.sign(kap) * rho
        lo = -np.inf if (k == 0 and kap == 0) else 0.0
        hi = np.inf if (k == m - 1 and kap == 0) else ln
        better = (sl >= lo) & (sl <= hi) & (np.abs(dl) < np.abs(best_d))
        best_s = np.where(better, s0 + sl, best_s)
        best_d = np.where(better, dl, best_d)
    return best_s, best_d


def tex_level(fp, texel0, nlev):
    """Finest mip level whose texels (texel0 * 2**level) are at least fp wide."""
    fp = np.asarray(fp, float)
    lv = np.zeros(fp.shape, np.int64)
    for lvl in range(nlev - 1):
        lv += texel0 * 2.0 ** lvl < fp
    return lv


def tex_sample(x, y, fp, k, tex, tex_inv, tex_off):
    """Nearest texel of texture k at world (x, y), at the level chosen for footprint fp."""
    nlev = tex_off.shape[1]
    lv = tex_level(fp, 1.0 / tex_inv[k], nlev)
    inv = tex_inv[k] * 0.5 ** lv
    n = np.int64(1) << (nlev - 1 - lv)
    with np.errstate(invalid="ignore"):
        i = np.nan_to_num(np.floor(x * inv)).astype(np.int64) % n
        j = np.nan_to_num(np.floor(y * inv)).astype(np.int64) % n
    return tex[tex_off[k, lv] + j * n + i].astype(np.float64)


def ground_albedo(x, y, fp, segs, g, tex, tex_inv, tex_off):
    """Ground albedo; noise from the mip-mapped textures at the level chosen for fp."""
    s, d = road_coords(x, y, segs)
    w = np.abs(d - g[0])
    seed = int(g[8])
    hw, lw, sw = g[1], g[2] / 2, g[4]
    asphalt = 0.16 + tex_sample(x, y, fp, 0, tex, tex_inv, tex_off)
    dashed = (w < lw) & ((s % g[6]) < g[5])
    asphalt = np.where(dashed | (np.abs(w - g[3]) < lw), 0.75, asphalt)
    sl = 1.2
    u = s % sl
    v = (w - hw) % sl
    slab = 0.36 + 0.1 * (hash3(np.floor(s / sl).astype(np.int64),
                               np.floor((w - hw) / sl).astype(np.int64), seed + 3) - 0.5)
    side = np.where(w < hw + 0.3, 0.45, np.where((u < 0.05) | (v < 0.05), 0.2, slab))
    if g[7] == 0:
        beyond = 0.1 + tex_sample(x, y, fp, 1, tex, tex_inv, tex_off)
    else:
        beyond = 0.3 + tex_sample(x, y, fp, 2, tex, tex_inv, tex_off)
    return np.where(w < hw, asphalt, np.where(w < hw + sw, side, beyond))


def box_point_albedo(mat, par, bid, u, z):
    """Albedo at (u, z) of a box face, per element."""
    mat = np.asarray(mat)
    p0, p1, p2, p3 = (par[..., i] for i in range(4))
    with np.errstate(divide="ignore", invalid="ignore"):
        fi = np.floor(z / p1)
        ci = np.floor(u / p2)
        fz = z / p1 - fi
        fu = u / p2 - ci
        fi_i = np.nan_to_num(fi).astype(np.int64)
        ci_i = np.nan_to_num(ci).astype(np.int64)
    grey = np.where((fz > 0.3) & (fz < 0.85) & (fu > 0.2) & (fu < 0.8),
                    0.06 + 0.2 * hash3(ci_i, fi_i, bid), p0 + 0.06 * (hash3(fi_i, bid, 77) - 0.5))
    orange = np.where((fz > 0.15) & (fz < 0.9) & (fu > 0.3) & (fu < 0.7),
                      0.1 + 0.15 * hash3(ci_i, fi_i, bid),
                      np.where((z % 0.6) < 0.06, p0 * 0.75, p0))
    lines = np.where((u % 1.0) < 0.12, 0.15, orange)
    car = np.where((z > p1) & (z < p2), 0.05, np.where(z < p3, 0.08, p0))
    return np.select([mat == 0, mat == 1, mat == 2, mat == 3], [p0, grey, orange, lines], car)


def box_albedo(mat, par, bid, u, z, wu):
    """Mean albedo over [u - wu/2, u + wu/2] at height z (wu = 0: the value at u): the interval
    is cut at every edge of the window columns (and of the vertical lines) and each piece,
    constant, weighs its length. Footprints beyond 64 window columns are cut to 64."""
    mat, u, z, wu = np.broadcast_arrays(np.asarray(mat), u, z, wu)
    par = np.broadcast_to(par, u.shape + (4,))
    bid = np.broadcast_to(bid, u.shape)
    out = np.empty(u.shape)
    for i in np.ndindex(u.shape):
        if not wu[i] > 0 or mat[i] in (0, 4):     # plain and car: nothing varies along u
            out[i] = box_point_albedo(mat[i], par[i], bid[i], u[i], z[i])
            continue
        cw = par[i][2]
        w = min(wu[i], 64 * cw)
        u0, u1 = u[i] - w / 2, u[i] + w / 2
        cuts = [u0, u1]
        for c in range(int(np.floor(u0 / cw)), int(np.floor(u1 / cw)) + 1):
            cuts += [c * cw, (c + 0.2) * cw, (c + 0.3) * cw, (c + 0.7) * cw, (c + 0.8) * cw]
        if mat[i] == 3:
            for m in range(int(np.floor(u0)), int(np.floor(u1)) + 1):
                cuts += [m, m + 0.12]
        cuts = np.unique(np.clip(cuts, u0, u1))
        mid = (cuts[1:] + cuts[:-1]) / 2
        val = box_point_albedo(np.full(len(mid), mat[i]), np.tile(par[i], (len(mid), 1)),
                               bid[i], mid, np.full(len(mid), z[i]))
        out[i] = np.sum(val * np.diff(cuts)) / (u1 - u0)
    return out


def rotation(psi, theta):
    """Camera-to-world rotation: yaw psi about world z, pitch theta (nose up), then eq. 3.4."""
    rz = np.array([[np.cos(psi), -np.sin(psi), 0], [np.sin(psi), np.cos(psi), 0], [0, 0, 1]])
    # nose up by theta: rotation about the vehicle's y (left) axis by -theta
    a = -theta
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    # columns: camera X, Y, Z in vehicle coordinates (thesis eq. 3.4)
    r_vc = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    return rz @ ry @ r_vc


def pitch(t, traj):
    if traj[8] == 0 or t < traj[7]:
        return 0.0
    amp, om, interval, decay, first = traj[3], 2 * np.pi * traj[4], traj[5], traj[6], traj[7]
    total = 0.0
    k = 0
    while first + k * interval <= t:
        u = t - (first + k * interval)
        total += amp * np.exp(-u / decay) * np.sin(om * u)
        k += 1
    return total


def pose(t, segs, traj):
    """(position, rotation) of the camera at time t (s), by walking the segments."""
    s = traj[0] + traj[1] * t
    k = 0
    while k < len(segs) - 1 and s >= segs[k + 1, 5]:
        k += 1
    x0, y0, h0, _, kap, s0 = segs[k, :6]
    u = s - s0
    if kap == 0:
        p, h = (x0 + u * np.cos(h0), y0 + u * np.sin(h0)), h0
    else:
        h = h0 + kap * u
        p = (x0 + (np.sin(h) - np.sin(h0)) / kap, y0 - (np.cos(h) - np.cos(h0)) / kap)
    turned = max(t - traj[12], 0.0)           # pan right (heading down), tilt up
    return (np.array([p[0], p[1], traj[2]]),
            rotation(h - traj[10] * turned, pitch(t, traj) + traj[11] * turned))


def rays(xs, ys, f, cx, cy, rot):
    """World directions (camera Z component 1) through pixel positions."""
    cam = np.stack([(xs - cx) / f, (ys - cy) / f, np.ones_like(xs)], axis=-1)
    return cam @ rot.T


def visible_columns(vis, bbox, f, cx, k, n):
    """Sample columns [c0, c1] of each visible box's projection's bounding rectangle (x0, x1 of
    bbox[vis[q]], normalised) with two samples' margin, clipped to [0, n - 1]; unbounded
    (|x| beyond 1e6 px) sides take the image's edge."""
    out = np.zeros((len(vis), 2), np.int64)
    for q, b in enumerate(vis):
        x0 = bbox[b, 0] * f + cx
        x1 = bbox[b, 1] * f + cx
        c0 = math.floor((x0 + 0.5) * k - 0.5) - 2 if x0 > -1e6 else 0
        c1 = math.ceil((x1 + 0.5) * k - 0.5) + 2 if x1 < 1e6 else n - 1
        out[q] = max(c0, 0), min(c1, n - 1)
    return out


def trace(o, d, boxes):
    """(t, kind, index, face) for every ray d [n, 3] from o, testing every box."""
    n = len(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where((d[:, 2] < 0) & (o[2] > 0), -o[2] / d[:, 2], np.inf)
        best = tg.copy()
        kind = np.where(np.isfinite(tg), 1, 0)
        idx = np.full(n, -1)
        face = np.full(n, -1)
        for b, box in enumerate(boxes):
            t1 = (box[:3] - o) / d
            t2 = (box[3:] - o) / d
            tn_ax = np.minimum(t1, t2)
            tf = np.minimum.reduce(np.maximum(t1, t2), axis=1)
            tn = tn_ax.max(axis=1)
            hit = (tn <= tf) & (tn > 0) & (tn < best)
            ax = np.argmax(tn_ax, axis=1)   # ties: first axis, as the kernel
            fc = 2 * ax + (d[np.arange(n), ax] <= 0)
            best = np.where(hit, tn, best)
            kind = np.where(hit, 2, kind)
            idx = np.where(hit, b, idx)
            face = np.where(hit, fc, face)
    return best, kind, idx, face


def shade(t, kind, idx, face, o, d, fp, wu, scene):
    """Intensity of every ray; fp: ground footprint of each ray's sample row; wu: the width over
    which box faces average their texture along u."""
    boxes, mats, pars = scene.boxes, scene.box_mat, scene.box_par
    light = scene.light
    n = np.linalg.norm(d, axis=1)
    sky = light[5] + (light[6] - light[5]) * np.maximum(d[:, 2] / n, 0)
    tt = np.where(np.isfinite(t), t, 0.0)
    p = o + tt[:, None] * d
    g = ground_albedo(p[:, 0], p[:, 1], fp, scene.segs, scene.ground, scene.tex, scene.tex_inv,
                      scene.tex_off) * (light[4] + light[3] * max(light[2], 0))
    bi = np.maximum(idx, 0)
    axis = np.maximum(face, 0) // 2
    sgn = np.where(face % 2 == 1, 1.0, -1.0)
    lam = np.maximum(sgn * light[np.minimum(axis, 2)], 0)
    u = np.where(axis == 0, p[:, 1], p[:, 0])
    alb = box_albedo(mats[bi], pars[bi], bi, u, p[:, 2], wu) if len(boxes) else np.zeros(len(t))
    alb = np.where(axis == 2, 0.8 * pars[bi, 0] if len(boxes) else 0.0, alb)
    bx = alb * (light[4] + light[3] * lam)
    return np.select([kind == 0, kind == 1], [sky, g], bx)


def box_footprint(t, face, o, xs, ys, rot, cam, h=1e-4):
    """|du / dx| (metres per pixel along the image row) on the side face each ray hit: the rays
    through x -+ h meet the face's plane at u -+; 0 where no side face was hit."""
    axis = np.where(face >= 0, face // 2, 2)
    side = axis < 2
    a = np.minimum(axis, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = rays(xs, ys, cam.f, cam.cx, cam.cy, rot)
        plane = o[a] + np.where(side, t, 0.0) * d[np.arange(len(t)), a]
        us = []
        for e in (-h, h):
            de = rays(xs + e, ys, cam.f, cam.cx, cam.cy, rot)
            te = (plane - o[a]) / de[np.arange(len(t)), a]
            us.append(o[1 - a] + te * de[np.arange(len(t)), 1 - a])
        return np.where(side, np.abs(us[1] - us[0]) / (2 * h), 0.0)


def render(scene, t_s):
    """Frame [H, W] with k x k supersampling, every ray against every box. The ground texture
    level of a sample row follows the row's largest ground footprint: the ground depth of the
    row times the sample spacing, stretched by the ray's grazing angle (|d|^2 / -d_z)."""
    cam = scene.camera
    k = cam.supersample
    o, rot = pose(t_s, scene.segs, scene.traj)
    sub = (np.arange(k) + 0.5) / k - 0.5
    ys, xs = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    acc = np.zeros(xs.shape)
    for b in sub:
        ds = [rays((xs + a).ravel(), (ys + b).ravel(), cam.f, cam.cx, cam.cy, rot) for a in sub]
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = -o[2] / ds[0][:, 2]          # ground depth, the same for the whole row
            fp_rays = [tg / (cam.f * k) * (d ** 2).sum(1) / -d[:, 2] for d in ds]
        fp = np.max([f.reshape(xs.shape) for f in fp_rays], axis=(0, 2))       # per row
        fp = np.repeat(fp, cam.width)
        for a, d in zip(sub, ds, strict=True):
            t, kind, idx, face = trace(o, d, scene.boxes)
            wu = box_footprint(t, face, o, xs.ravel() + a, ys.ravel() + b, rot, cam) * \
                TEXTURE_FOOTPRINT / k
            acc += shade(t, kind, idx, face, o, d, fp, wu, scene).reshape(xs.shape)
    return acc / (k * k)


def project(points, t_s, scene):
    o, rot = pose(t_s, scene.segs, scene.traj)
    pc = (points - o) @ rot
    cam = scene.camera
    uv = np.stack([cam.f * pc[:, 0] / pc[:, 2] + cam.cx, cam.f * pc[:, 1] / pc[:, 2] + cam.cy], 1)
    return uv, pc


def depth(xs, ys, t_s, scene):
    cam = scene.camera
    o, rot = pose(t_s, scene.segs, scene.traj)
    d = rays(np.asarray(xs, float), np.asarray(ys, float), cam.f, cam.cx, cam.cy, rot)
    return trace(o, d, scene.boxes)[0]


def object_id(xs, ys, t_s, scene):
    """What every ray sees: its box's index, -2 for the ground, -1 for the sky."""
    cam = scene.camera
    o, rot = pose(t_s, scene.segs, scene.traj)
    d = rays(np.asarray(xs, float), np.asarray(ys, float), cam.f, cam.cx, cam.cy, rot)
    _, kind, idx, _ = trace(o, d, scene.boxes)
    return np.select([kind == 2, kind == 1], [idx, -2], -1)


def flow_fd(xs, ys, t_s, scene, h=1e-6):
    """Motion field by central differences: re-project the 3-D point seen at (x, y, t)."""
    cam = scene.camera
    o, rot = pose(t_s, scene.segs, scene.traj)
    d = rays(np.asarray(xs, float), np.asarray(ys, float), cam.f, cam.cx, cam.cy, rot)
    t = trace(o, d, scene.boxes)[0]
    pts = o + t[:, None] * d
    a, _ = project(pts, t_s + h, scene)
    b, _ = project(pts, t_s - h, scene)
    v = (a - b) / (2 * h)
    return v[:, 0], v[:, 1]


def row_speed2_max(xbs, yb, tb, f, vc, wc):
    """Largest squared motion-field speed (px/s)^2 over samples (xbs, yb) at depths tb;
    samples whose speed is NaN (zero depth) are skipped, 0 if none is left."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        rho = 1.0 / tb
        u = ((-vc[0] + xbs * vc[2]) * rho + wc[0] * xbs * yb - wc[1] * (1.0 + xbs * xbs)
             + wc[2] * yb)
        v = ((-vc[1] + yb * vc[2]) * rho + wc[0] * (1.0 + yb * yb) - wc[1] * xbs * yb
             - wc[2] * xbs)
        m2 = u * u + v * v
    m2 = m2[~np.isnan(m2)]
    return (max(0.0, float(m2.max())) if m2.size else 0.0) * f * f
