"""Numba kernels of the scene renderer: a frame rendered row by row, k x k samples per pixel,
each sample row traced against the ground and the visible boxes (nearest first, only the
sample columns of a box's projection) and shaded in passes; the largest image speed over the samples
bounds the next time step.

Entry points: :func:`render` (a frame), :func:`render_rows` (every jstep-th row of a frame,
for threads) and :func:`render_row_set` (chosen rows, each with its own speed bound), all on
a :class:`~evchain.kernels.scene_geometry.FrameView` (the frame's camera and visible boxes) and
a :class:`~evchain.kernels.scene_geometry.WorldArrays` (array layouts in
:mod:`evchain.kernels.scene_geometry`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from evchain.kernels.scene_geometry import INF
from evchain.kernels.scene_shading import (
    TEXTURE_FOOTPRINT,
    box_pass,
    face_light,
    ground_levels,
    ground_pass,
)

_J = dict(cache=True, error_model="numpy")
_I = dict(cache=True, error_model="numpy", inline="always")   # helpers of the hot loops
# kernels called per row with array arguments: compiled without reference counting (numba's
# counts on every array argument, atomic operations that its pruning pass keeps where they
# straddle branches; docs/explanation/scene.md, "Rendering"); they allocate nothing
_R = dict(cache=True, error_model="numpy", _nrt=False)


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


@njit(**_R)
def row_vmax2(tm, yb, tb, f, vc, wc, m2):
    """Largest squared motion-field magnitude (px/s)^2 over the samples of a row at yb with
    depths tb[c] (the columns' terms tm from :func:`flow_terms`: the same operations as
    :func:`~evchain.kernels.scene_geometry.flow_at`, in its order); m2: scratch [n]. (Two
    loops, both vectorised.)"""
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


@njit(**_J)
def level_work(ntex):
    """Per-row texture level scratch: inverse texel sizes, offsets, masks."""
    return np.empty(ntex), np.empty(ntex, np.int64), np.empty(ntex, np.int64)


@njit(**_J)
def visible_columns(vis, bbox, f, cx, k, n):
    """Sample columns [c0, c1] that the q-th visible box vis[q] can cover in any row (its
    projection's bounding rectangle bbox, with a margin of two samples): int64 [nvis, 2]."""
    vcol = np.empty((vis.shape[0], 2), np.int64)
    for q in range(vis.shape[0]):
        bq = vis[q]
        c0 = 0
        c1 = n - 1
        bx0 = bbox[bq, 0] * f + cx
        bx1 = bbox[bq, 1] * f + cx
        if bx0 > -1e6:
            c0 = max(c0, int(math.floor((bx0 + 0.5) * k - 0.5)) - 2)
        if bx1 < 1e6:
            c1 = min(c1, int(math.ceil((bx1 + 0.5) * k - 0.5)) + 2)
        vcol[q, 0] = c0
        vcol[q, 1] = c1
    return vcol


@njit(**_J)
def row_work(n):
    """Scratch arrays of one sample row of n samples: float64 [8, n], int32 [3, n] (small
    enough to stay in the L1 cache with the rest) and the per-block depth bound of blocks of 16
    samples; the last pair is r0, r1 of the row whose directions the scratch holds (NaN: none)."""
    return (np.empty((8, n)), np.empty((3, n), np.int32), np.empty(n // 16 + 1),
            np.full(2, np.nan))


@njit(**_R)
def render_row(j, pos, rot, vc, wc, f, cx, cy, k, boxes, box_mat, box_par, segs, ground, light,
               lit, tex, tex_inv, tex_off, vis, minz, bbox, vcol, xbs, tm, pcol, fw, iw, bmax,
               rprev, lv_inv, lv_off, lv_mask, acc, out):
    """Render image row j into out[j]; return the largest squared image speed of its first
    sample row (the time step's bound on motion: the k sample rows of a pixel row differ by
    less than a pixel).

    Per sample row: the ground hit is one division (no roll: every ray of a row has the same
    world dz); each visible box whose projection's bounding rectangle contains the row gets its
    exact z-slab for the row; boxes are visited nearest-first and only the samples of the
    frame's column range of the box (vcol[q]: :func:`visible_columns`) whose current hit is
    farther than the box's nearest corner get the exact slab test (blocks of 16 samples whose
    farthest current hit is nearer are skipped whole). The result equals testing every box for
    every sample.

    lit: :func:`face_light`; tm: :func:`flow_terms`; pcol: pixel column of every sample;
    fw, iw, bmax, rprev: scratch (:func:`row_work`, kept between the rows of one frame);
    acc: [W]. The arguments are those of :func:`render_rows`' records, unpacked: passed as
    records to this per-row call they cost 5 % of the frame rate."""
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
            c0 = vcol[q, 0]
            c1 = vcol[q, 1]
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


@njit(cache=True, error_model="numpy", nogil=True)
def render_rows(frame, world, out, j0, jstep):
    """:func:`render` of the rows j0, j0 + jstep, ... only: threads render interleaved rows of
    one frame (the same result).

    Parameters
    ----------
    frame : FrameView
        The frame's camera (pose, velocities, intrinsics, supersampling k) and visible boxes.
    world : WorldArrays
        The world.
    out : ndarray, float32 [H, W]
        The frame: linear intensity, the mean of each pixel's k x k samples; rows j0,
        j0 + jstep, ... are written.
    j0, jstep : int
        The first row and the step between rows.

    Returns
    -------
    float
        The largest motion-field magnitude (px/s) over the first sample row of each of the
        rows.
    """
    h = out.shape[0]
    row_v2 = np.zeros(h)
    render_row_set(frame, world, out, np.arange(h), j0, jstep, row_v2)
    vmax2 = 0.0
    for j in range(j0, h, jstep):
        if row_v2[j] > vmax2:
            vmax2 = row_v2[j]
    return math.sqrt(vmax2)


@njit(cache=True, error_model="numpy", nogil=True)
def render_row_set(frame, world, out, rows, i0, istep, row_v2):
    """Render the rows ``rows[i0], rows[i0 + istep], ...`` of a frame into ``out`` (the same
    values as :func:`render` in those rows; threads take interleaved entries) and write each
    one's largest squared motion-field magnitude, (px/s)^2 over its first sample row, into
    ``row_v2[row]`` (float64 [H]); other rows of ``out`` and ``row_v2`` are left as they are."""
    w = out.shape[1]
    k = frame.k
    xbs = sample_columns(w, k, frame.cx, frame.f)
    tm = flow_terms(xbs, frame.vc, frame.wc)
    pcol = pixel_columns(w, k)
    fw, iw, bmax, rprev = row_work(w * k)
    lv_inv, lv_off, lv_mask = level_work(world.tex_inv.shape[0])
    acc = np.empty(w)
    lit = face_light(world.light)
    vcol = visible_columns(frame.vis, frame.bbox, frame.f, frame.cx, k, w * k)
    for i in range(i0, rows.shape[0], istep):
        j = rows[i]
        row_v2[j] = render_row(j, frame.pos, frame.rot, frame.vc, frame.wc, frame.f, frame.cx,
                               frame.cy, k, world.boxes, world.box_mat, world.box_par,
                               world.segs, world.ground, world.light, lit, world.tex,
                               world.tex_inv, world.tex_off, frame.vis, frame.minz, frame.bbox,
                               vcol, xbs, tm, pcol, fw, iw, bmax, rprev, lv_inv, lv_off, lv_mask,
                               acc, out)


@njit(cache=True, error_model="numpy", nogil=True)
def render(frame, world, out):
    """Render one frame.

    Parameters
    ----------
    frame : FrameView
        The frame's camera (pose and velocities from
        :func:`~evchain.kernels.scene_geometry.camera_state`, intrinsics, supersampling k) and
        its visible boxes, nearest first, with their depth bounds
        (:func:`~evchain.kernels.scene_culling.frame_boxes`).
    world : WorldArrays
        The world.
    out : ndarray, float32 [H, W]
        Written: linear intensity, the mean of each pixel's k x k samples.

    Returns
    -------
    float
        The largest motion-field magnitude (px/s) over the samples of every pixel row's first
        sample row (the adaptive time step's bound).
    """
    return render_rows(frame, world, out, 0, 1)
