"""Numba kernel of ``foe_fit``: the heading and the rotation of the camera from normal-flow
magnitudes with a piecewise-planar scene.

A point at image position p with inverse time to contact ``g`` seen by a camera translating
towards the FOE and turning at ``w`` has flow ``(p - foe) g + B(p) w``, where ``B(p) w`` is the
rotational flow of a pinhole camera (independent of depth). Its normal flow along the unit
normal n has speed ``s = (p - foe).n g + c.Om`` with ``Om = f w`` in px/s (the rotational flow
at the principal point) and ``c = n.B(p) / f`` (:func:`rotation_coefficients`). Three planes
are modelled, each with its own scale: the road seen by a level camera (``g = a0 dy``, ``dy = y
- y_foe`` rows below the FOE), a facade left of the FOE (``g = a1 (x_foe - x)``) and one right
of it (``g = a2 (x - x_foe)``). A side's buildings stand at different setbacks (``a = V / (f
D)`` at lateral distance D), so each side is split into depth bands (a facade point ``|dx|`` px
beside the FOE lies at depth ``Z = f D / |dx|``, band ``floor(band_px / |dx|)``, the last band
taking the rest), each with its own ratio to the side's scale, ``th[NP:]`` (left bands, then
right; none: one scale per side). The events' bands are those at the FOE's column where the
Gauss-Newton iterations start; the ratios are refitted after them from the last iteration's
weights, the FOE and the scales held (:func:`_update_bands`), and tied to 1 by a ridge, so that
a band with few events keeps the side's scale and the FOE's column stays constrained by how the
speeds vary within each band. Unknowns ``th = (x_foe, y_foe, a0, a1, a2)`` and the rotation
``om[k]`` of every slab ``k``: the events of a fit span several hundred ms while the rotation
changes faster (a pitch oscillation at 2 Hz), so it is piecewise constant in time, one ``Om``
per slab of ``slab_us`` counted back from the fit time T (slab k: times in ``[T - (k + 1)
slab_us, T - k slab_us)``). Everything is fitted jointly every time, nothing is carried from
earlier fits but the starting point: rotation and a shifted FOE explain much of each other's
flow, and a rotation fixed from earlier fits lets that shared part drift.

Pitch (turning about the camera's x axis) also moves the heading in the image, since a car's
heading does not follow its pitch: every event is first mapped into the camera frame of the
fit time by the rotation about the x axis between its time and T, integrated from the slabs'
pitch rates at the start of the fit (:func:`warp_pitch`); there the FOE and the road plane are
those of time T. Yaw is not undone: a car's heading turns with its yaw, so in the camera frame
the FOE stays.

A fit is iteratively reweighted Gauss-Newton: every event within ``margin`` px of a plane's
vanishing line is left out of that plane; each remaining event is assigned to the plane that
predicts its speed best and weighs ``w_t (1 - (e/c)^2)^2 / pred^2`` (Tukey on the residual
relative to the predicted speed, ``e = |s - pred| / pred``, decay ``w_t`` by age): the flow's
error grows with the true speed, of which ``pred`` (translation and rotation) is the model's
estimate; dividing by the measured ``s`` instead favours speeds measured too slow. Events
without a positive prediction are left out. The normal equations have an arrow shape (each
slab's 3 x 3 block, the 5 shared unknowns coupling all) and are solved through the Schur
complement of the slab blocks. A plane's scale without a value starts as the weighted median
of ``(s - c.Om) / ((p - foe).n d)`` over its events with ``(p - foe).n > 0``; for the facades
only of events above the FOE's row, where a level camera sees no road (below it the road's
events, far more numerous, would set the facades' scales several times too large, a wrong
local minimum the fit does not leave).

The unknowns a fit may change are chosen per call (``free``: the FOE's column, each rotation
axis, the FOE's row and the road's scale together); the others keep their values. Rotation
and scales feed each other's starting values:
a cold start (scales unknown) alternates scales from the rotations and each slab's rotation
from the scales by least absolute residuals (:func:`_slab_l1`), which reaches a rotation far
from its start where the Tukey weights would reject the whole slab; a warm start does that for
the newest slab only (a curve's sudden yaw). After the fit, the same is done for the newest
slab with every axis free (``probe``): how fast the camera turns about the axes the fit held.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import literally, njit

#: the shared unknowns ``th``: the FOE (px) and the three planes' scales (road, left, right
#: facade; 1/(s px))
FOE_X, FOE_Y, ROAD, LEFT, RIGHT = range(5)
NP = 5
#: rounds of scales from the rotations and rotations from the scales in a cold start, and
#: iterations of :func:`_slab_l1`
COLD_ROUNDS = 3
L1_ITER = 8
#: sums per slab of :func:`_pass`: 6 of the 3 x 3 block, 6 with the FOE, 9 with the planes
#: (road, left, right x the 3 axes), 3 of the right-hand side
NS = 24


class FitEvents(NamedTuple):
    """The flow events a fit sees (one entry per event, in time order)."""

    x: np.ndarray   #: position, px (float64)
    y: np.ndarray
    nx: np.ndarray  #: unit normal (the flow's direction)
    ny: np.ndarray
    s: np.ndarray   #: normal flow speed, px/s (> 0)
    e: np.ndarray   #: decay weight exp((t - t_ref) / tau)
    c0: np.ndarray  #: rotational normal speed per unit ``Om`` (:func:`rotation_coefficients`)
    c1: np.ndarray
    c2: np.ndarray
    t: np.ndarray   #: time, µs (int64)


class FitParams(NamedTuple):
    """Constants of :func:`fit`; build with :func:`evchain.kernels.records.record`."""

    margin: float     #: events this close to a plane's vanishing line are left out of it, px
    tolerance: float  #: Tukey constant on the relative speed residual
    max_iter: int     #: Gauss-Newton iterations
    max_step: float   #: largest FOE step per iteration, px
    min_step: float   #: a fit whose FOE step is below this has converged, px
    slab_us: int      #: the rotation is constant within slabs of this length, µs
    f: float          #: focal length, px
    cx: float         #: principal point, px
    cy: float
    band_px: float    #: a facade event ``|dx|`` px beside the FOE is in depth band
    #: ``floor(band_px / |dx|)`` (the last band takes the rest)
    band_prior: float  #: decayed weight that ties each band's ratio to 1 (a ridge)


def initial_theta(foe_x: float, foe_y: float, n_bands: int = 0) -> np.ndarray:
    """Shared unknowns for a fit starting at the FOE (foe_x, foe_y), the planes' scales
    unknown, followed by ``n_bands`` depth bands' scale ratios per facade (left, then right;
    NaN: 1)."""
    th = np.full(NP + 2 * n_bands, np.nan)
    th[FOE_X] = foe_x
    th[FOE_Y] = foe_y
    return th


def rotation_coefficients(x, y, nx, ny, f: float, cx: float, cy: float):
    """``(c0, c1, c2)``: the normal speed (px/s) that a rotation ``Om = f w`` (px/s) gives an
    event at (x, y) with unit normal (nx, ny) is ``c0 Om_x + c1 Om_y + c2 Om_z``. With
    ``X = (x - cx) / f``, ``Y = (y - cy) / f`` the rotational flow is
    ``u = f (X Y wx - (1 + X^2) wy + Y wz)``, ``v = f ((1 + Y^2) wx - X Y wy - X wz)``
    (Longuet-Higgins and Prazdny 1980; :class:`~evchain.core.truth.RotationTruth`). The filter
    gets them per packet from :func:`flow_columns`, whose copy of this expression
    test_foe_fit.py holds to these values bit for bit."""
    X = (np.asarray(x, np.float64) - cx) / f
    Y = (np.asarray(y, np.float64) - cy) / f
    return (nx * X * Y + ny * (1.0 + Y * Y), -nx * (1.0 + X * X) - ny * X * Y, nx * Y - ny * X)


@njit(cache=True, nogil=True, error_model="numpy")
def flow_columns(x, y, vx, vy, f, cx, cy, rotation, ox, oy, onx, ony, os_, oc0, oc1, oc2, keep):
    """A packet's flow events as the fit's columns, the moving ones (speed > 0) only, in order
    from index 0 of the outputs: position ``ox, oy`` (px), unit normal ``onx, ony``, speed
    ``os_`` (px/s) and, with ``rotation``, :func:`rotation_coefficients` ``oc0, oc1, oc2`` (else
    0). ``keep[i]``: whether event i moves. Returns how many do. The same values, bit for bit,
    as those numpy expressions on float64 (test_foe_fit.py), in one pass without temporaries."""
    m = 0
    for i in range(len(x)):
        u = np.float64(vx[i])
        v = np.float64(vy[i])
        s = math.hypot(u, v)
        keep[i] = s > 0.0
        if not s > 0.0:
            continue
        xi = np.float64(x[i])
        yi = np.float64(y[i])
        nx = u / s
        ny = v / s
        ox[m] = xi
        oy[m] = yi
        onx[m] = nx
        ony[m] = ny
        os_[m] = s
        if rotation:
            X = (xi - cx) / f
            Y = (yi - cy) / f
            oc0[m] = nx * X * Y + ny * (1.0 + Y * Y)
            oc1[m] = -nx * (1.0 + X * X) - ny * X * Y
            oc2[m] = nx * Y - ny * X
        else:
            oc0[m] = 0.0
            oc1[m] = 0.0
            oc2[m] = 0.0
        m += 1
    return m


@njit(cache=True, error_model="numpy")
def solve(A, b):
    """x with A x = b by Gaussian elimination with partial pivoting (A, b are overwritten);
    returns False when a pivot is zero."""
    n = len(b)
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[p, k]):
                p = i
        if A[p, k] == 0.0:
            return False
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            b[k], b[p] = b[p], b[k]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= f * A[k, j]
            b[i] -= f * b[k]
    for k in range(n - 1, -1, -1):
        acc = b[k]
        for j in range(k + 1, n):
            acc -= A[k, j] * b[j]
        b[k] = acc / A[k, k]
    return True


@njit(cache=True, error_model="numpy")
def slab_bounds(t, i0, i1, T, slab_us, n_slabs):
    """``lo[k], hi[k]``: the events ``i0 <= i < i1`` of slab k (times in ``[T - (k + 1)
    slab_us, T - k slab_us)``), as indices from ``i0``; ``t`` sorted."""
    lo = np.zeros(n_slabs, np.int64)
    hi = np.zeros(n_slabs, np.int64)
    tt = t[i0:i1]
    for k in range(n_slabs):
        hi[k] = np.searchsorted(tt, T - k * slab_us)
        lo[k] = np.searchsorted(tt, T - (k + 1) * slab_us)
    return lo, hi


@njit(cache=True, error_model="numpy", fastmath={"reassoc", "contract"})
def warp_pitch(events, i0, T, lo, hi, om, prm, xw, yw, mx, my):
    """Each event seen in the camera frame of time T: turned about the camera's x axis by the
    pitch ``b`` from T back to its time, integrated from the slabs' pitch rates
    ``om[k, 0] / f`` (rad/s), a ray (X, Y, 1) becomes (X, Y cos b - sin b, Y sin b + cos b).
    Writes for the event ``i0 + j`` the position (px) ``xw[j]``, ``yw[j]`` and ``m = J^-T n``
    into ``mx[j]``, ``my[j]``, the normal mapped so that ``m . v' = n . v`` for a flow v' in the
    new frame (J: the map's Jacobian; m is not unit). ``|b|`` is small (a fraction of a
    radian): sine and cosine by their series to 5th and 4th order (error below 1e-8 at
    0.1 rad)."""
    x, y, nx, ny, t = events.x, events.y, events.nx, events.ny, events.t
    inv_f = 1.0 / prm.f
    cx, cy, f = prm.cx, prm.cy, prm.f
    end = 0.0  # pitch at the slab's later end, relative to T (rad)
    for k in range(len(lo)):
        rate = om[k, 0] * inv_f * 1e-6  # rad/us
        t_end = T - k * prm.slab_us
        for j in range(lo[k], hi[k]):
            b = end - rate * (t_end - t[i0 + j])
            b2 = b * b
            sb = b * (1.0 - b2 * (1.0 / 6.0 - b2 * (1.0 / 120.0)))
            cb = 1.0 - b2 * (0.5 - b2 * (1.0 / 24.0))
            X = (x[i0 + j] - cx) * inv_f
            Y = (y[i0 + j] - cy) * inv_f
            D = sb * Y + cb
            iD = 1.0 / D
            xw[j] = cx + f * X * iD
            yw[j] = cy + f * (cb * Y - sb) * iD
            mx[j] = D * nx[i0 + j]
            my[j] = X * sb * D * nx[i0 + j] + D * D * ny[i0 + j]
        end -= rate * prm.slab_us


@njit(cache=True, error_model="numpy", inline="always")
def _lever(k, dxx, dyy):
    """The plane's factor d: dy for the road, -dx left, dx right."""
    if k == 0:
        return dyy
    return -dxx if k == 1 else dxx


@njit(cache=True, error_model="numpy", inline="always")
def _applies(k, dxx, dyy, margin):
    if k == 0:
        return dyy > margin
    return -dxx > margin if k == 1 else dxx > margin


@njit(cache=True, error_model="numpy", inline="always")
def _band_index(dxx, nb, band_px):
    """Index into the band ratios ``th[NP:]`` of a facade event ``dxx`` px beside the FOE: its
    depth band ``floor(band_px / |dx|)`` (at most ``nb - 1``) on its side (left first).
    Branch-free; ``nb`` is at least 1."""
    top = nb - 1.0
    q = band_px / abs(dxx) if dxx != 0.0 else top
    return int(min(q, top)) + (0 if dxx < 0.0 else nb)


@njit(cache=True, error_model="numpy")
def _weighted_median(r, w, m):
    """The weighted median of ``r[:m]`` (weights ``w[:m]``): the first value in sorted order
    where the cumulative weight reaches half the total; NaN when none does."""
    o = np.argsort(r[:m])
    half = 0.0
    for j in range(m):
        half += w[j]
    half *= 0.5
    acc = 0.0
    for j in range(m):
        acc += w[o[j]]
        if acc >= half:
            return r[o[j]]
    return np.nan


@njit(cache=True, error_model="numpy")
def _init_scales(w, lo, hi, om, g, th, margin):
    """Each plane scale without a value: the weighted median of (s - c.Om) / ((p - foe).n d)
    over the plane's events with (p - foe).n > 0 (the facades' only above the FOE's row); left
    NaN without events. ``w``: the window of :func:`_window`."""
    xw, yw, mx, my, s, e, c0, c1, c2 = w
    n = len(xw)
    for k in range(3):
        if not math.isnan(th[ROAD + k]):
            continue
        rr = np.empty(n)
        ww = np.empty(n)
        m = 0
        for q in range(len(lo)):
            for j in range(lo[q], hi[q]):
                dxx = xw[j] - th[FOE_X]
                dyy = yw[j] - th[FOE_Y]
                dn = dxx * mx[j] + dyy * my[j]
                if dn > 0.0 and _applies(k, dxx, dyy, margin) and (k == 0 or dyy < -margin):
                    rot = c0[j] * om[q, 0] + c1[j] * om[q, 1] + c2[j] * om[q, 2]
                    rr[m] = (s[j] - rot) / (dn * _lever(k, dxx, dyy))
                    ww[m] = e[j] * g
                    m += 1
        if m > 0:
            med = _weighted_median(rr, ww, m)
            if not math.isnan(med):
                th[ROAD + k] = med


@njit(cache=True, error_model="numpy")
def _slab_l1(w, a, b, g, th, om, k, margin, c, n_iter, free, rat, nb, band_px):
    """A robust start for slab k's rotation with the shared unknowns held: ``n_iter``
    iteratively reweighted least-squares steps towards the least relative residual
    ``sum w_t rho(|s - pred| / s)`` over the slab's events ``a <= j < b`` (each assigned to the
    plane predicting it best), rho Huber's: squared up to the Tukey constant ``c``, absolute
    beyond (a pure absolute residual passes through a few events and is ill-conditioned).
    Unlike the Tukey weights of the fit, this reaches a rotation far from the start (a curve's
    sudden yaw, a cold start) and is pulled little by outliers. Axes that are not ``free`` keep
    their values. ``rat``: the facades' band ratios (``nb`` per side, :func:`_band_index`)."""
    xw, yw, mx, my, s, e, c0, c1, c2 = w
    K = np.empty((3, 3))
    h = np.empty(3)
    C = np.empty((3, NP))
    for _ in range(n_iter):
        K[:] = 0.0
        h[:] = 0.0
        o0, o1, o2 = om[k, 0], om[k, 1], om[k, 2]
        h0 = 0.0 if free[1] else o0  # the held axes' part of the rotation
        h1 = 0.0 if free[2] else o1
        h2 = 0.0 if free[3] else o2
        for j in range(a, b):
            dxx = xw[j] - th[FOE_X]
            dyy = yw[j] - th[FOE_Y]
            dn = dxx * mx[j] + dyy * my[j]
            rot = c0[j] * o0 + c1[j] * o1 + c2[j] * o2
            rho = rat[_band_index(dxx, nb, band_px)]
            err = np.inf
            pt = 0.0
            for q in range(3):
                if math.isnan(th[ROAD + q]) or not _applies(q, dxx, dyy, margin):
                    continue
                pq = th[ROAD + q] * dn * _lever(q, dxx, dyy) * (rho if q else 1.0)
                eq = abs(s[j] - pq - rot)
                if eq < err:
                    err, pt = eq, pq
            if err == np.inf:
                continue
            wt = e[j] * g / (s[j] * max(err, c * s[j]))
            z0, z1, z2 = c0[j], c1[j], c2[j]
            rr = s[j] - pt - (z0 * h0 + z1 * h1 + z2 * h2)
            K[0, 0] += wt * z0 * z0
            K[0, 1] += wt * z0 * z1
            K[0, 2] += wt * z0 * z2
            K[1, 1] += wt * z1 * z1
            K[1, 2] += wt * z1 * z2
            K[2, 2] += wt * z2 * z2
            h[0] += wt * z0 * rr
            h[1] += wt * z1 * rr
            h[2] += wt * z2 * rr
        K[1, 0], K[2, 0], K[2, 1] = K[0, 1], K[0, 2], K[1, 2]
        _hold(K, C, h, free)
        tr = K[0, 0] + K[1, 1] + K[2, 2]
        if not tr > 0.0:
            return
        for q in range(3):
            K[q, q] += 1e-9 * tr
        good, inv = _inverse3(K)
        if not good:
            return
        for q in range(3):
            if free[1 + q]:
                om[k, q] = inv[q, 0] * h[0] + inv[q, 1] * h[1] + inv[q, 2] * h[2]


@njit(cache=True, error_model="numpy", inline="always")
def _event(dxx, dyy, mxj, myj, sj, rot, wti, a0, al, ar, rho, has_road, has_l, has_r, margin,
           c):
    """The model at one event (translational part from the FOE offset ``dxx, dyy`` and the
    normal ``mxj, myj``, rotational part ``rot``, decay weight ``wti``, the ratio ``rho`` of its
    facade's depth band), assigned to the plane predicting it best (road wins ties):
    (applicable weight, inlier weight, robust weight, residual, J0, J1, Ja, is road, is left
    facade, is right facade); Ja is the derivative by the plane's scale (a facade's: the
    side's). Branch-free."""
    dn = dxx * mxj + dyy * myj
    road_ok = has_road and dyy > margin
    left = dxx < 0.0
    adx = abs(dxx)
    a_s = (al if left else ar) * rho
    side_ok = adx > margin and (has_l if left else has_r)
    pr = a0 * dn * dyy + rot
    ps = a_s * dn * adx + rot
    er = abs(sj - pr) if road_ok else np.inf
    es = abs(sj - ps) if side_ok else np.inf
    use_side = es < er
    re = es if use_side else er
    pred = ps if use_side else pr
    valid = re < np.inf and pred > 0.0
    u = re / (pred * c) if valid else 1.0
    inlier = u < 1.0
    v = 1.0 - u * u
    wt = wti * v * v / (pred * pred) if inlier else 0.0
    sg = 1.0 if left else -1.0
    j0 = sg * a_s * (mxj * dxx + dn) if use_side else -a0 * mxj * dyy
    j1 = sg * a_s * myj * dxx if use_side else -a0 * (myj * dyy + dn)
    ja = dn * adx * rho if use_side else dn * dyy
    mr = 0.0 if use_side else 1.0
    ml = 1.0 if use_side and left else 0.0
    mq = 1.0 if use_side and not left else 0.0
    return (wti if valid else 0.0, wti if inlier else 0.0, wt, sj - pred, j0, j1, ja, mr, ml,
            mq)


@njit(cache=True, error_model="numpy", inline="always")
def _scales(th):
    """(a0, al, ar, has_road, has_l, has_r): the planes' scales, 0 where unknown."""
    has_road = not math.isnan(th[2])
    has_l = not math.isnan(th[3])
    has_r = not math.isnan(th[4])
    return (th[2] if has_road else 0.0, th[3] if has_l else 0.0, th[4] if has_r else 0.0,
            has_road, has_l, has_r)


@njit(cache=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _sums(w, a, b, om0, om1, om2, g, th, margin, c, rho, out, with_slab, with_rot):
    """One Gauss-Newton pass over the events ``a <= j < b`` of one slab with rotation
    ``(om0, om1, om2)``: adds the 19 shared sums to ``out[:19]`` (a00, a01, a11, b0, b1,
    inlier weight, applicable weight, then per plane road / left / right: w J0 Ja, w J1 Ja,
    w Ja Ja, w r Ja) and, with ``with_slab``, writes the slab's :data:`NS` sums of its rotation
    to ``out[19:]`` (w c c^T: 00 01 02 11 12 22; w c J0, w c J1 per axis; w c Ja per plane and
    axis; w r c per axis). ``rho[j]``: the ratio of event j's facade band. Without
    ``with_rot`` (a slab that does not turn, its rotation 0) the rotation coefficients are not
    read and every rotational speed is 0: the same sums up to the rounding of their order, a
    third less memory read. ``with_slab`` and ``with_rot`` are compile-time constants
    (``literally``): each pair compiles its own loop. Branch-free (selects, one accumulator
    per sum, reassociated) so that LLVM vectorises it; the sums' order differs from a plain
    loop only in rounding. The loop stores nothing: with a store per event LLVM checks at run
    time how far the stored array lies from each array read and runs the vectorised or the
    scalar loop accordingly, so the sums' last bits depended on where the arrays lay in memory
    (:func:`_band_terms` writes the per-event terms). The loop counts in unsigned integers:
    numba's indexing then has no case for negative indices, whose selects made the vectorised
    loop about twice as slow."""
    literally(with_slab)
    literally(with_rot)
    xw, yw, mx, my, s, e, cc0, cc1, cc2 = w
    xf, yf = th[0], th[1]
    a0, al, ar, has_road, has_l, has_r = _scales(th)
    a00 = a01 = a11 = b0 = b1 = inl = tot = 0.0
    r0 = r1 = r2 = r3 = l0 = l1 = l2 = l3 = q0 = q1 = q2 = q3 = 0.0
    k00 = k01 = k02 = k11 = k12 = k22 = 0.0
    f00 = f01 = f10 = f11 = f20 = f21 = 0.0
    p0r = p1r = p2r = p0l = p1l = p2l = p0q = p1q = p2q = 0.0
    h0 = h1 = h2 = 0.0
    for j in range(np.uint64(a), np.uint64(b)):
        if with_rot:
            z0, z1, z2 = cc0[j], cc1[j], cc2[j]
            rot = z0 * om0 + z1 * om1 + z2 * om2
        else:
            z0 = z1 = z2 = rot = 0.0
        vw, iw, wt, res, j0, j1, ja, mr, ml, mq = _event(
            xw[j] - xf, yw[j] - yf, mx[j], my[j], s[j], rot, e[j] * g, a0, al, ar, rho[j],
            has_road, has_l, has_r, margin, c)
        tot += vw
        inl += iw
        wr = wt * res
        wj0 = wt * j0
        wj1 = wt * j1
        a00 += wj0 * j0
        a01 += wj0 * j1
        a11 += wj1 * j1
        b0 += wr * j0
        b1 += wr * j1
        d0 = wj0 * ja
        d1 = wj1 * ja
        d2 = wt * ja * ja
        d3 = wr * ja
        r0 += mr * d0
        r1 += mr * d1
        r2 += mr * d2
        r3 += mr * d3
        l0 += ml * d0
        l1 += ml * d1
        l2 += ml * d2
        l3 += ml * d3
        q0 += mq * d0
        q1 += mq * d1
        q2 += mq * d2
        q3 += mq * d3
        if with_slab:
            w0 = wt * z0
            w1 = wt * z1
            w2 = wt * z2
            k00 += w0 * z0
            k01 += w0 * z1
            k02 += w0 * z2
            k11 += w1 * z1
            k12 += w1 * z2
            k22 += w2 * z2
            f00 += w0 * j0
            f01 += w0 * j1
            f10 += w1 * j0
            f11 += w1 * j1
            f20 += w2 * j0
            f21 += w2 * j1
            p0r += w0 * ja * mr
            p1r += w1 * ja * mr
            p2r += w2 * ja * mr
            p0l += w0 * ja * ml
            p1l += w1 * ja * ml
            p2l += w2 * ja * ml
            p0q += w0 * ja * mq
            p1q += w1 * ja * mq
            p2q += w2 * ja * mq
            h0 += wr * z0
            h1 += wr * z1
            h2 += wr * z2
    shared = (a00, a01, a11, b0, b1, inl, tot, r0, r1, r2, r3, l0, l1, l2, l3, q0, q1, q2, q3)
    for i in range(19):
        out[i] += shared[i]
    if with_slab:
        slab = (k00, k01, k02, k11, k12, k22, f00, f01, f10, f11, f20, f21,
                p0r, p1r, p2r, p0l, p1l, p2l, p0q, p1q, p2q, h0, h1, h2)
        for i in range(NS):
            out[19 + i] = slab[i]


@njit(cache=True, error_model="numpy")
def _pass(w, lo, hi, om, g, th, margin, c, rho, rotating, shared, slabs):
    """One Gauss-Newton pass over every slab: the 19 shared sums into ``shared`` and, when
    some rotation axis is free (``rotating``), each slab's :data:`NS` sums into ``slabs[k]``
    (see :func:`_sums`; else they are 0)."""
    out = np.zeros(19 + NS)
    slabs[:] = 0.0
    for k in range(len(lo)):
        if rotating:
            out[19:] = 0.0
            _sums(w, lo[k], hi[k], om[k, 0], om[k, 1], om[k, 2], g, th, margin, c, rho, out,
                  True, True)
            slabs[k, :] = out[19:]
        elif om[k, 0] != 0.0 or om[k, 1] != 0.0 or om[k, 2] != 0.0:
            _sums(w, lo[k], hi[k], om[k, 0], om[k, 1], om[k, 2], g, th, margin, c, rho, out,
                  False, True)
        else:  # no rotation: rot is 0 for every event, and the coefficients are not read
            _sums(w, lo[k], hi[k], 0.0, 0.0, 0.0, g, th, margin, c, rho, out, False, False)
    shared[:] = out[:19]


@njit(cache=True, error_model="numpy")
def _band_terms(w, lo, hi, om, g, th, margin, c, rho, u1, u2):
    """The per-event terms of the band ratios' sums (:func:`_update_bands`) at the model of a
    pass (the same ``th``, ``om``, ``rho`` as :func:`_pass`): for each event assigned to a
    facade, with its predicted translational speed q and robust weight w, ``u1[j] = w q (s -
    c.Om)`` and ``u2[j] = w q^2`` (0 for the road's and the rest). One element-wise loop per
    slab without sums and without fastmath: the same bits however it is vectorised (unsigned
    indices, as in :func:`_sums`). A slab that does not turn is run without reading the
    rotation coefficients: its rotational speeds, finite coefficients times 0, are zeros,
    which change no term."""
    xw, yw, mx, my, s, e, cc0, cc1, cc2 = w
    xf, yf = th[0], th[1]
    a0, al, ar, has_road, has_l, has_r = _scales(th)
    for k in range(len(lo)):
        om0, om1, om2 = om[k, 0], om[k, 1], om[k, 2]
        if om0 != 0.0 or om1 != 0.0 or om2 != 0.0:
            for j in range(np.uint64(lo[k]), np.uint64(hi[k])):
                rot = cc0[j] * om0 + cc1[j] * om1 + cc2[j] * om2
                u1[j], u2[j] = _band_term(xw[j] - xf, yw[j] - yf, mx[j], my[j], s[j], rot,
                                          e[j] * g, a0, al, ar, rho[j], has_road, has_l,
                                          has_r, margin, c)
        else:
            for j in range(np.uint64(lo[k]), np.uint64(hi[k])):
                u1[j], u2[j] = _band_term(xw[j] - xf, yw[j] - yf, mx[j], my[j], s[j], 0.0,
                                          e[j] * g, a0, al, ar, rho[j], has_road, has_l,
                                          has_r, margin, c)


@njit(cache=True, error_model="numpy", inline="always")
def _band_term(dxx, dyy, mxj, myj, sj, rot, wti, a0, al, ar, rho, has_road, has_l, has_r,
               margin, c):
    """One event's terms ``(u1, u2)`` of :func:`_band_terms` (arguments as :func:`_event`)."""
    _, _, wt, res, _, _, _, mr, _, _ = _event(dxx, dyy, mxj, myj, sj, rot, wti, a0, al, ar, rho,
                                              has_road, has_l, has_r, margin, c)
    tr = sj - rot
    q = tr - res  # the predicted translational speed
    wf = wt - mr * wt
    return wf * q * tr, wf * q * q


@njit(cache=True, error_model="numpy")
def _bands(xw, x_foe, nb, band_px, rat, bi, rho):
    """Each event's facade band ``bi[j]`` (:func:`_band_index`, from the FOE's column
    ``x_foe``; int32, half the memory of a float64 to write and read back) and its ratio
    ``rho[j] = rat[bi[j]]``. Two loops: the bands' alone vectorises, the look-up of the ratios
    does not (unsigned indices, as in :func:`_sums`)."""
    for j in range(np.uint64(len(xw))):
        bi[j] = _band_index(xw[j] - x_foe, nb, band_px)
    for j in range(np.uint64(len(xw))):
        rho[j] = rat[np.uint64(bi[j])]


@njit(cache=True, error_model="numpy")
def _update_bands(bi, u1, u2, rat, prior):
    """Each facade depth band's scale ratio ``rat[i]`` from the per-event terms of the last
    pass (:func:`_band_terms`, the events' bands ``bi``): the robustly weighted least-squares
    ratio of its events' translational speed ``s - c.Om`` to the side's prediction ``P = a (p
    - foe).n |dx|`` (their predicted speed over the band's ratio), tied to 1 by ``prior``
    (decayed weight): ``(sum w P (s - c.Om) + prior) / (sum w P^2 + prior)``."""
    n = len(rat)
    num = np.zeros(n)
    den = np.zeros(n)
    for j in range(len(bi)):
        i = int(bi[j])
        num[i] += u1[j]
        den[i] += u2[j]
    for i in range(n):
        r = rat[i]
        if den[i] > 0.0:
            num[i] /= r
            den[i] /= r * r
        rat[i] = (num[i] + prior) / (den[i] + prior)


@njit(cache=True, error_model="numpy")
def _shared_system(sm, A, b):
    """The 5 x 5 Gauss-Newton system of the shared unknowns from the sums of
    :func:`_sums` (J is 0 off each event's plane)."""
    A[:] = 0.0
    b[:] = 0.0
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = sm[0], sm[1], sm[1], sm[2]
    b[0], b[1] = sm[3], sm[4]
    for k in range(3):  # per plane: w J0 Ja, w J1 Ja, w Ja Ja, w r Ja
        A[0, 2 + k] = A[2 + k, 0] = sm[7 + 4 * k]
        A[1, 2 + k] = A[2 + k, 1] = sm[8 + 4 * k]
        A[2 + k, 2 + k] = sm[9 + 4 * k]
        b[2 + k] = sm[10 + 4 * k]


@njit(cache=True, error_model="numpy")
def _slab_system(sl, K, C, h):
    """A slab's block ``K`` (3 x 3, w c c^T), its coupling ``C`` to the shared unknowns
    (3 x 5, w c J^T) and right-hand side ``h`` (w r c) from its sums."""
    K[0, 0], K[0, 1], K[0, 2] = sl[0], sl[1], sl[2]
    K[1, 0], K[1, 1], K[1, 2] = sl[1], sl[3], sl[4]
    K[2, 0], K[2, 1], K[2, 2] = sl[2], sl[4], sl[5]
    for a in range(3):
        C[a, FOE_X] = sl[6 + 2 * a]
        C[a, FOE_Y] = sl[7 + 2 * a]
        for p in range(3):
            C[a, ROAD + p] = sl[12 + 3 * p + a]
        h[a] = sl[21 + a]


@njit(cache=True, error_model="numpy")
def _condition(A, b, free):
    """Keep a plane's scale without events, the FOE's column unless ``free[0]``, and the FOE's
    row and the road's scale when ``free`` has a fifth entry that is False (their row and column
    become the identity, no step), and add a 1e-9 ridge relative to the trace; False when the
    trace is not positive. Returns the kept unknowns as a mask."""
    keep = np.zeros(NP, np.bool_)
    tr = 0.0
    for p in range(NP):
        tr += A[p, p]
    if not tr > 0.0:
        return False, keep
    for p in range(NP):
        held = (p == FOE_X and not free[0]) or (
            (p == FOE_Y or p == ROAD) and len(free) > 4 and not free[4])
        if A[p, p] <= 1e-12 * tr or held:  # keep the value
            keep[p] = True
            for q in range(NP):
                A[p, q] = 0.0
                A[q, p] = 0.0
            A[p, p] = 1.0
            b[p] = 0.0
        else:
            A[p, p] += 1e-9 * tr
    return True, keep


@njit(cache=True, error_model="numpy")
def _hold(K, C, h, free):
    """Hold the rotation axes that are not free (``free[1 + a]`` False): their rows and
    columns of a slab's block become the identity, their coupling and right-hand side 0."""
    for a in range(3):
        if not free[1 + a]:
            K[a, :] = 0.0
            K[:, a] = 0.0
            K[a, a] = 1.0
            C[a, :] = 0.0
            h[a] = 0.0


@njit(cache=True, error_model="numpy")
def _inverse3(K):
    """(True, the inverse) of a symmetric 3 x 3 matrix with a positive determinant (adjugate
    over determinant), else (False, undefined values)."""
    a, b_, c = K[0, 0], K[0, 1], K[0, 2]
    d, e, f = K[1, 1], K[1, 2], K[2, 2]
    i00 = d * f - e * e
    i01 = c * e - b_ * f
    i02 = b_ * e - c * d
    det = a * i00 + b_ * i01 + c * i02
    inv = np.empty((3, 3))
    if not det > 0.0:
        return False, inv
    inv[0, 0] = i00 / det
    inv[0, 1] = inv[1, 0] = i01 / det
    inv[0, 2] = inv[2, 0] = i02 / det
    inv[1, 1] = (a * f - c * c) / det
    inv[1, 2] = inv[2, 1] = (b_ * c - a * e) / det
    inv[2, 2] = (a * d - b_ * b_) / det
    return True, inv


@njit(cache=True, error_model="numpy")
def _step(shared, slabs, A, b, d_om, free):
    """The Gauss-Newton step: ``b`` (the shared unknowns' step) and ``d_om`` (each slab's)
    from the arrow-shaped system, by the Schur complement of the slab blocks. A slab without
    events (a block with no positive trace) keeps its rotation. False when singular."""
    _shared_system(shared, A, b)
    ok, keep = _condition(A, b, free)
    if not ok:
        return False
    n = slabs.shape[0]
    K = np.empty((3, 3))
    C = np.empty((3, NP))
    h = np.empty(3)
    invs = np.zeros((n, 3, 3))
    live = np.zeros(n, np.bool_)
    for k in range(n):
        _slab_system(slabs[k], K, C, h)
        tr = K[0, 0] + K[1, 1] + K[2, 2]
        if not tr > 0.0:
            continue
        _hold(K, C, h, free)
        for a in range(3):
            K[a, a] += 1e-9 * tr
        good, inv = _inverse3(K)
        if not good:
            continue
        live[k] = True
        invs[k] = inv
        for a in range(3):
            for p in range(NP):
                if keep[p]:
                    C[a, p] = 0.0
        # A -= C^T K^-1 C, b -= C^T K^-1 h
        KC = inv @ C
        Kh = inv @ h
        for p in range(NP):
            for q in range(NP):
                A[p, q] -= C[0, p] * KC[0, q] + C[1, p] * KC[1, q] + C[2, p] * KC[2, q]
            b[p] -= C[0, p] * Kh[0] + C[1, p] * Kh[1] + C[2, p] * Kh[2]
    if not solve(A, b):
        return False
    for k in range(n):
        if not live[k]:
            d_om[k, :] = 0.0
            continue
        _slab_system(slabs[k], K, C, h)
        _hold(K, C, h, free)
        for a in range(3):
            acc = h[a]
            for p in range(NP):
                if not keep[p]:
                    acc -= C[a, p] * b[p]
            h[a] = acc
        for a in range(3):
            d_om[k, a] = invs[k, a, 0] * h[0] + invs[k, a, 1] * h[1] + invs[k, a, 2] * h[2]
    return True


@njit(cache=True, error_model="numpy")
def _apply_step(th, om, b, d_om, max_step):
    """th += b, om += d_om, the FOE's part shortened to ``max_step`` px; returns (the FOE step
    before shortening, px; every value finite, or NaN for a scale without a value)."""
    step = max(abs(b[FOE_X]), abs(b[FOE_Y]))
    scale = 1.0 if step <= max_step else max_step / step
    for p in range(NP):
        th[p] += b[p] * (scale if p < 2 else 1.0)
    for p in range(NP):
        if not math.isfinite(th[p]) and not (p >= ROAD and math.isnan(th[p])):
            return step, False
    for k in range(om.shape[0]):
        for a in range(3):
            om[k, a] += d_om[k, a]
            if not math.isfinite(om[k, a]):
                return step, False
    return step, True


@njit(cache=True, error_model="numpy")
def _window(events, i0, i1, T, lo, hi, om, prm):
    """The fitted events ``i0 <= i < i1`` as seen in the camera frame of the fit time (warped
    positions and normals, :func:`warp_pitch`) with their speeds, weights and rotation
    coefficients, indexed from 0."""
    s, e = events.s[i0:i1], events.e[i0:i1]
    c0, c1, c2 = events.c0[i0:i1], events.c1[i0:i1], events.c2[i0:i1]
    if not np.any(om[:, 0] != 0.0):  # no pitch: the events as they are
        return (events.x[i0:i1], events.y[i0:i1], events.nx[i0:i1], events.ny[i0:i1], s, e,
                c0, c1, c2)
    n = i1 - i0
    xw = np.empty(n)
    yw = np.empty(n)
    mx = np.empty(n)
    my = np.empty(n)
    warp_pitch(events, i0, T, lo, hi, om, prm, xw, yw, mx, my)
    return (xw, yw, mx, my, s, e, c0, c1, c2)


@njit(cache=True, error_model="numpy", nogil=True)
def fit(events, i0, i1, T, g, th, om, free, probe, prm):
    """Fit the shared unknowns ``th`` and the slabs' rotations ``om`` to the events
    ``i0..i1``; robust Gauss-Newton (module docstring).

    NaN scales are initialised first. The events weigh ``e g``: ``e = exp((t - t_ref) / tau)``
    is kept per event (computed once), ``g = exp(-(T - t_ref) / tau)`` per fit, so an event at
    the fit time T weighs 1.

    Parameters
    ----------
    events : FitEvents
        float64 arrays: positions (px), unit normals, speeds (px/s, > 0), decay weights,
        rotation coefficients; int64 times (µs), sorted.
    i0, i1 : int
        The events fitted: ``i0 <= i < i1``, all before T.
    T : int
        The fit time, µs.
    g : float
        The fit time's decay factor (see above).
    th : float64 ndarray, shape (5,)
        In/out: the FOE (px, entries :data:`FOE_X`, :data:`FOE_Y`) and the road's, left and
        right facades' scales (1/(s px): :data:`ROAD`, :data:`LEFT`, :data:`RIGHT`; NaN:
        unknown).
    om : float64 ndarray, shape (n_slabs, 3)
        In/out: the rotation ``Om = f w`` (px/s) of every slab, ``om[0]`` the latest; the
        pitch rates at entry set the warp. Slabs without events keep their values.
    free : bool ndarray, shape (4,) or (5,)
        Which unknowns the fit may change: ``free[0]`` the FOE's column, ``free[1 + a]``
        rotation axis a in every slab, ``free[4]`` (True when absent) the FOE's row and the
        road's scale together; the others keep their values.
    probe : float64 ndarray, shape (3,)
        Out: the newest slab's rotation refitted with every axis free and the rest held (the
        robust start of :func:`_slab_l1`), px/s; whether a held axis turns.
    prm : FitParams
        The constants.

    Returns
    -------
    (bool, float, float)
        ok (False when a system is singular or a value is not finite), the decayed inlier
        weight and the decayed weight of the events the model applies to.
    """
    n_slabs = om.shape[0]
    lo, hi = slab_bounds(events.t, i0, i1, T, prm.slab_us, n_slabs)
    w = _window(events, i0, i1, T, lo, hi, om, prm)
    nb = (len(th) - NP) // 2
    for q in range(2):  # a side without a scale, and a band without a ratio, start at 1
        for i in range(NP + q * nb, NP + (q + 1) * nb):
            if math.isnan(th[LEFT + q]) or math.isnan(th[i]):
                th[i] = 1.0
    rat = th[NP:] if nb else np.ones(2)
    nbe = max(nb, 1)
    unknown = np.isnan(th[ROAD:NP])
    if unknown.any():  # a cold start: scales and rotations from each other, robustly
        for _ in range(COLD_ROUNDS):
            th[ROAD:NP][unknown] = np.nan
            _init_scales(w, lo, hi, om, g, th, prm.margin)
            for k in range(n_slabs):
                _slab_l1(w, lo[k], hi[k], g, th, om, k, prm.margin, prm.tolerance, L1_ITER,
                         free, rat, nbe, prm.band_px)
            w = _window(events, i0, i1, T, lo, hi, om, prm)
        th[ROAD:NP][unknown] = np.nan
        _init_scales(w, lo, hi, om, g, th, prm.margin)
    elif n_slabs and (free[1] or free[2] or free[3]):  # the newest slab: however far its
        # rotation jumped
        _slab_l1(w, lo[0], hi[0], g, th, om, 0, prm.margin, prm.tolerance, L1_ITER, free,
                 rat, nbe, prm.band_px)
    rotating = free[1] or free[2] or free[3]
    n = i1 - i0
    rho, u1, u2, bi = np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.int32)
    if nb:  # the facades' bands at the FOE's column where the fit starts
        _bands(w[0], th[FOE_X], nb, prm.band_px, rat, bi, rho)
    else:
        rho[:] = 1.0
    A = np.zeros((NP, NP))
    b = np.zeros(NP)
    shared = np.zeros(19)
    slabs = np.zeros((n_slabs, NS))
    d_om = np.zeros((n_slabs, 3))
    th_pass = th.copy()  # the model of the last pass, for the bands' update
    om_pass = om.copy()
    inl = 0.0
    tot = 0.0
    for _ in range(prm.max_iter):
        if nb:
            th_pass[:] = th
            om_pass[:] = om
        _pass(w, lo, hi, om, g, th, prm.margin, prm.tolerance, rho, rotating, shared, slabs)
        inl, tot = shared[5], shared[6]
        if not _step(shared, slabs, A, b, d_om, free):
            return False, inl, tot
        step, finite = _apply_step(th, om, b, d_om, prm.max_step)
        if not finite:
            return False, inl, tot
        if step < prm.min_step:  # a warm-started fit moves less after 1-2 iterations
            break
    if nb and prm.max_iter > 0:  # the bands' ratios for the next fit, from the last pass
        _band_terms(w, lo, hi, om_pass, g, th_pass, prm.margin, prm.tolerance, rho, u1, u2)
        _update_bands(bi, u1, u2, rat, prm.band_prior)
    if n_slabs:  # the newest slab's rotation with every axis free, the rest held
        first = om[:1].copy()
        _slab_l1(w, lo[0], hi[0], g, th, first, 0, prm.margin, prm.tolerance, L1_ITER,
                 np.ones(4, np.bool_), rat, nbe, prm.band_px)
        probe[:] = first[0]
    return True, inl, tot
