"""Plain numpy reference of the ``foe_fit`` kernel, and piecewise-planar flow generators (with
and without the camera's rotation)."""

from __future__ import annotations

import numpy as np


def slab_of(t, T, slab_us):
    """The slab of each time: k for t in [T - (k + 1) slab_us, T - k slab_us)."""
    return (T - 1 - np.asarray(t, np.int64)) // slab_us


def rotation_coefficients(x, y, nx, ny, f, cx, cy):
    """c with n . B(p) w = c . (f w): the rotational flow of a pinhole camera, projected."""
    X, Y = (x - cx) / f, (y - cy) / f
    u = np.stack([X * Y, -(1 + X * X), Y], 1)  # u = f (u . w)
    v = np.stack([1 + Y * Y, -X * Y, -X], 1)
    return nx[:, None] * u + ny[:, None] * v


def pitch_back(t, T, slab_us, om, f):
    """The camera's pitch at times t relative to T (rad), integrated from the slabs' pitch
    rates om[k, 0] / f."""
    k = slab_of(t, T, slab_us)
    rate = om[:, 0] / f * 1e-6
    end = -np.concatenate([[0.0], np.cumsum(rate * slab_us)])[:len(om)]
    return end[k] - rate[k] * ((T - k * slab_us) - t)


def warp(x, y, nx, ny, b, f, cx, cy, series=False):
    """Positions and mapped normals ``m = J^-T n`` in the frame turned by pitch b (rad) about
    the camera's x axis: a ray (X, Y, 1) becomes (X, Y cos b - sin b, Y sin b + cos b)."""
    X, Y = (x - cx) / f, (y - cy) / f
    if series:  # as the kernel: sine and cosine by their series to 5th and 4th order
        sb = b - b ** 3 / 6 + b ** 5 / 120
        cb = 1 - b ** 2 / 2 + b ** 4 / 24
    else:
        sb, cb = np.sin(b), np.cos(b)
    D = sb * Y + cb
    J = np.zeros((len(x), 2, 2))  # d(xw, yw) / d(x, y)
    J[:, 0, 0] = 1 / D
    J[:, 0, 1] = -X * sb / D ** 2
    J[:, 1, 1] = 1 / D ** 2
    m = np.linalg.solve(np.transpose(J, (0, 2, 1)), np.stack([nx, ny], 1)[..., None])[..., 0]
    return cx + f * X / D, cy + f * (cb * Y - sb) / D, m[:, 0], m[:, 1]


def band_ratio(dxx, th, band_px):
    """Each event's facade band ratio: band ``min(floor(band_px / |dx|), nb - 1)`` of the
    ``nb`` bands on its side (``th[5:]``: left, then right); 1 without bands."""
    nb = (len(th) - 5) // 2
    if nb == 0:
        return np.ones(len(dxx))
    band = np.minimum(np.floor(band_px / np.where(dxx != 0, np.abs(dxx), 1.0)), nb - 1)
    band = np.where(dxx != 0, band, nb - 1).astype(np.int64)
    return th[5:][band + np.where(dxx < 0, 0, nb)]


def _band_of(dxx, th, band_px):
    nb = (len(th) - 5) // 2
    band = np.minimum(np.floor(band_px / np.where(dxx != 0, np.abs(dxx), 1.0)), nb - 1)
    band = np.where(dxx != 0, band, nb - 1).astype(np.int64)
    return band + np.where(dxx < 0, 0, nb)


def _geometry(x, y, nx, ny, th, margin, band_px=1.0, rho=None):
    """Offsets from the FOE, (p - foe).n, the planes' factors d (road dy, left -dx, right dx;
    a facade's times its band ratio ``rho``, by default that of its band at ``th``) and where
    each plane applies."""
    dxx, dyy = x - th[0], y - th[1]
    dn = dxx * nx + dyy * ny
    rho = band_ratio(dxx, th, band_px) if rho is None else rho
    lev = np.stack([dyy, -dxx, dxx], 1)
    app = lev > margin
    return dxx, dyy, dn, lev * np.stack([np.ones(len(x)), rho, rho], 1), app


def _init_scales(x, y, nx, ny, s, wt, rot, th, margin):
    """Each NaN scale: the weighted median of (s - rot) / ((p - foe).n d) over the plane's events
    with (p - foe).n > 0 (the facades' only above the FOE's row)."""
    dxx, dyy, dn, lev, app = _geometry(x, y, nx, ny, th[:5], margin)
    for p in range(3):
        ini = app[:, p] & (dn > 0) & ((dyy < -margin) if p else True)
        if np.isnan(th[2 + p]) and ini.any():
            r = (s - rot)[ini] / (dn * lev[:, p])[ini]
            w = wt[ini]
            o = np.argsort(r, kind="quicksort")
            th[2 + p] = r[o][np.argmax(np.cumsum(w[o]) >= 0.5 * w.sum())]


def slab_l1(x, y, nx, ny, s, wt, cc, th, om_k, margin, c, n_iter, free, band_px=1.0):
    """The kernel's ``_slab_l1`` on one slab's (warped) events: ``n_iter`` reweighted least
    squares steps towards min sum wt huber_c(|s - pred| / s) for the free axes, the others held;
    returns the slab's rotation (om_k is copied)."""
    om_k = np.array(om_k, np.float64)
    held = ~np.asarray(free[1:4], bool)
    dxx, dyy, dn, lev, app = _geometry(x, y, nx, ny, th, margin, band_px)
    app &= ~np.isnan(th[2:5])[None, :]
    for _ in range(n_iter):
        rot = cc @ om_k
        pt = np.where(app, th[2:5][None, :] * dn[:, None] * lev, np.nan)
        err = np.where(app, np.abs(s[:, None] - pt - rot[:, None]), np.inf)
        p = np.argmin(err, 1)
        idx = np.arange(len(s))
        use = np.isfinite(err[idx, p])
        e, ptk = err[idx, p][use], pt[idx, p][use]
        w = wt[use] / (s[use] * np.maximum(e, c * s[use]))
        z = cc[use]
        r = s[use] - ptk - z[:, held] @ om_k[held]
        K = (z * w[:, None]).T @ z
        h = (z * w[:, None]).T @ r
        K[held, :] = 0.0
        K[:, held] = 0.0
        K[held, held] = 1.0
        h[held] = 0.0
        tr = np.trace(K)
        if not tr > 0:
            return om_k
        K += 1e-9 * tr * np.eye(3)
        if not np.linalg.det(K) > 0:
            return om_k
        sol = np.linalg.solve(K, h)
        om_k[~held] = sol[~held]
    return om_k


def fit(x, y, nx, ny, s, t, T, tau_us, th, om, free, margin, c, max_iter, max_step, slab_us,
        f, cx, cy, cold_rounds=3, l1_iter=8, min_step=0.05, band_px=190.3, band_prior=20.0):
    """Same contract as ``evchain.kernels.foe_fit.fit`` on the given events with t < T in the
    slabs of ``om`` (th, om are copied; ``th[5:]`` the facades' band ratios, left then right);
    returns (ok, th, om, inlier weight, total, probe)."""
    th, om = np.array(th, np.float64), np.array(om, np.float64)
    nb = (len(th) - 5) // 2
    for q in range(2):  # a side without a scale, and a band without a ratio, start at 1
        r = th[5 + q * nb:5 + (q + 1) * nb]
        r[np.isnan(r) | np.isnan(th[3 + q])] = 1.0
    free = np.asarray(free, bool)
    t = np.asarray(t, np.int64)
    k = slab_of(t, T, slab_us)
    use = (t < T) & (k < len(om))
    x, y, nx, ny, s, t, k = (v[use] for v in (x, y, nx, ny, s, t, k))
    wt = np.exp(-(T - t) / tau_us)
    cc = rotation_coefficients(x, y, nx, ny, f, cx, cy)
    raw = (x, y, nx, ny)

    def warped():  # the kernel's series: a cold start's weighted medians amplify 1e-9 px;
        # without pitch the events as they are (a warp by 0 moves them by rounding)
        if not (om[:, 0] != 0).any():
            return raw
        return warp(*raw, pitch_back(t, T, slab_us, om, f), f, cx, cy, series=True)

    x, y, nx, ny = warped()
    probe = np.zeros(3)
    unknown = np.isnan(th[2:5])
    if unknown.any():  # cold start: scales and rotations from each other
        for _ in range(cold_rounds):
            th[2:5][unknown] = np.nan
            _init_scales(x, y, nx, ny, s, wt, np.einsum("ij,ij->i", cc, om[k]), th, margin)
            for q in range(len(om)):
                m = k == q
                om[q] = slab_l1(x[m], y[m], nx[m], ny[m], s[m], wt[m], cc[m], th, om[q],
                                margin, c, l1_iter, free, band_px)
            x, y, nx, ny = warped()
        th[2:5][unknown] = np.nan
        _init_scales(x, y, nx, ny, s, wt, np.einsum("ij,ij->i", cc, om[k]), th, margin)
    elif free[1:4].any() and len(om):
        m = k == 0
        om[0] = slab_l1(x[m], y[m], nx[m], ny[m], s[m], wt[m], cc[m], th, om[0], margin, c,
                        l1_iter, free, band_px)
    inl = tot = 0.0
    ns = 5 + 3 * len(om)
    # the bands at the column where the iterations start
    band = _band_of(x - th[0], th, band_px) if nb else None
    rho = th[5:][band] if nb else np.ones(len(x))
    for _ in range(max_iter):
        th_pass, om_pass = th.copy(), om.copy()
        A, b, inl, tot = normal_equations(x, y, nx, ny, s, wt, cc, k, th, om, margin, c,
                                          band_px, rho)
        if not free[1:4].any():  # no rotation unknowns
            A[5:, :] = 0.0
            A[:, 5:] = 0.0
            b[5:] = 0.0
        tr = np.trace(A[:5, :5])
        if not tr > 0:
            return False, th, om, inl, tot, probe
        for p in range(5):
            road_held = len(free) > 4 and not free[4]  # the FOE's row and the road's scale
            if A[p, p] <= 1e-12 * tr or (p == 0 and not free[0]) or (p in (1, 2) and road_held):
                A[p, :] = 0.0
                A[:, p] = 0.0
                A[p, p] = 1.0
                b[p] = 0.0
            else:
                A[p, p] += 1e-9 * tr
        for q in range(5, ns, 3):  # a slab without events keeps its rotation
            blk = slice(q, q + 3)
            trs = np.trace(A[blk, blk])
            if not trs > 0:
                A[blk, :] = 0.0
                A[:, blk] = 0.0
                A[blk, blk] = np.eye(3)
                b[blk] = 0.0
                continue
            A[blk, blk] += 1e-9 * trs * np.eye(3)
            for a in range(3):
                if not free[1 + a]:  # a held axis
                    A[q + a, :] = 0.0
                    A[:, q + a] = 0.0
                    A[q + a, q + a] = 1.0
                    b[q + a] = 0.0
        try:
            d = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            return False, th, om, inl, tot, probe
        step = max(abs(d[0]), abs(d[1]))
        d[:2] *= 1.0 if step <= max_step else max_step / step
        th[:5] += d[:5]
        om = om + d[5:].reshape(-1, 3)
        if not np.isfinite(th[:2]).all() or np.isinf(th[2:5]).any() or \
                not np.isfinite(om).all():
            return False, th, om, inl, tot, probe
        if step < min_step:  # px, as the kernel
            break
    if nb:  # from the last pass
        th[5:] = band_ratios(x, y, nx, ny, s, wt, cc, k, th_pass, om_pass, margin, c, rho,
                             band, band_prior)
    if len(om):
        m = k == 0
        probe = slab_l1(x[m], y[m], nx[m], ny[m], s[m], wt[m], cc[m], th, om[0], margin, c,
                        l1_iter, np.ones(4, bool), band_px)
    return True, th, om, inl, tot, probe


def _assign(x, y, nx, ny, s, wt, cc, k, th, om, margin, c, rho):
    """Each event's plane (the one predicting it best, road wins ties), robust weight,
    rotational speed and prediction, as in one Gauss-Newton pass."""
    dxx, dyy, dn, lev, app = _geometry(x, y, nx, ny, th, margin, rho=rho)
    app &= ~np.isnan(th[2:5])[None, :]
    rot = np.einsum("ij,ij->i", cc, om[k])
    pred = np.where(app, th[2:5][None, :] * dn[:, None] * lev + rot[:, None], np.nan)
    res = np.where(app, np.abs(s[:, None] - pred), np.inf)
    p = np.argmin(res, 1)
    idx = np.arange(len(s))
    pk = pred[idx, p]
    use = np.isfinite(res[idx, p]) & (pk > 0)
    u = np.where(use, res[idx, p] / np.where(use, pk, 1.0) / c, np.inf)
    inlier = use & (u < 1)
    w = np.where(inlier, wt * (1 - u * u) ** 2 / np.where(inlier, pk, 1.0) ** 2, 0.0)
    return p, w, rot, pk


def band_ratios(x, y, nx, ny, s, wt, cc, k, th, om, margin, c, rho, band, prior):
    """The facades' band ratios after a pass at ``th``, ``om`` with the events' ratios
    ``rho`` and bands ``band``: per band, over the events the pass assigns to a facade,
    ``(sum w P (s - rot) + prior) / (sum w P^2 + prior)`` with ``P`` the side's prediction
    (the translational prediction over the band's ratio) and ``w`` the robust weight."""
    p, w, rot, pk = _assign(x, y, nx, ny, s, wt, cc, k, th, om, margin, c, rho)
    fac = (w > 0) & (p > 0)
    pb = (pk - rot)[fac] / rho[fac]
    n = len(th) - 5
    num = np.bincount(band[fac], w[fac] * pb * (s - rot)[fac], n)
    den = np.bincount(band[fac], w[fac] * pb * pb, n)
    return (num + prior) / (den + prior)


def normal_equations(x, y, nx, ny, s, wt, cc, k, th, om, margin, c, band_px=1.0, rho=None):
    """One Gauss-Newton pass at ``th``, ``om`` with decay weights ``wt`` on warped events:
    (J^T W J, J^T W r, inlier weight, applicable weight) over the shared unknowns and every
    slab's rotation (columns 5 + 3 k ...); a facade's scale is its side's times its band's
    ratio (``rho`` per event, by default from ``th[5:]``), its column in J the side's."""
    if rho is None:
        rho = band_ratio(x - th[0], th, band_px)
    dxx, dyy, dn, lev, app = _geometry(x, y, nx, ny, th, margin, rho=rho)
    app &= ~np.isnan(th[2:5])[None, :]
    rot = np.einsum("ij,ij->i", cc, om[k])
    pred = np.where(app, th[2:5][None, :] * dn[:, None] * lev + rot[:, None], np.nan)
    res = np.where(app, np.abs(s[:, None] - pred), np.inf)
    p = np.argmin(res, 1)  # the plane predicting the speed best (road wins ties)
    idx = np.arange(len(s))
    pk = pred[idx, p]
    use = np.isfinite(res[idx, p]) & (pk > 0)
    u = np.where(use, res[idx, p] / np.where(use, pk, 1.0) / c, np.inf)
    tot = wt[use].sum()
    inlier = use & (u < 1)
    inl = wt[inlier].sum()
    w = np.where(inlier, wt * (1 - u * u) ** 2 / np.where(inlier, pk, 1.0) ** 2, 0.0)
    a = th[2 + p] * np.where(p > 0, rho, 1.0)
    J = np.zeros((len(s), 5 + 3 * len(om)))
    m0, m1, m2 = inlier & (p == 0), inlier & (p == 1), inlier & (p == 2)
    J[m0, 0] = (-a * nx * dyy)[m0]
    J[m0, 1] = (-a * (ny * dyy + dn))[m0]
    J[m1, 0] = (a * (nx * dxx + dn))[m1]
    J[m1, 1] = (a * ny * dxx)[m1]
    J[m2, 0] = (-a * (nx * dxx + dn))[m2]
    J[m2, 1] = (-a * ny * dxx)[m2]
    J[inlier, 2 + p[inlier]] = (dn * lev[idx, p])[inlier]
    for axis in range(3):
        J[inlier, 5 + 3 * k[inlier] + axis] = cc[inlier, axis]
    r = np.where(inlier, s - pk, 0.0)
    A = (J * w[:, None]).T @ J
    b = (J * w[:, None]).T @ r
    return A, b, inl, tot


def planar_flow(n, foe, a, rng, width=320, height=240, noise=0.0, outliers=0.0):
    """``n`` normal-flow events of a road (below the FOE, 1/tau = a[0] dy) and two facades
    (left / right of it, 1/tau = a[1] |dx|, a[2] |dx|) seen under pure translation, on pixel
    centres; random
    edge normals, relative speed noise ``noise``, a share ``outliers`` of random flow.
    Returns x, y, nx, ny, s (float64), the flow being s (nx, ny)."""
    xf, yf = foe
    x = rng.integers(0, width, n).astype(np.float64)
    y = rng.integers(0, height, n).astype(np.float64)
    dxx, dyy = x - xf, y - yf
    # which plane: road below the FOE when its depth is larger than the facade's
    g_road = np.where(dyy > 0, a[0] * dyy, 0.0)
    g_fac = np.where(dxx < 0, a[1] * -dxx, a[2] * dxx)
    g = np.maximum(g_road, g_fac)
    ang = rng.uniform(0, 2 * np.pi, n)
    nx, ny = np.cos(ang), np.sin(ang)
    dn = dxx * nx + dyy * ny
    flip = dn < 0
    nx[flip], ny[flip], dn[flip] = -nx[flip], -ny[flip], -dn[flip]
    s = dn * g * (1 + noise * rng.standard_normal(n))
    bad = rng.random(n) < outliers
    s[bad] = rng.uniform(1, 200, bad.sum())
    keep = s > 1e-3
    return x[keep], y[keep], nx[keep], ny[keep], s[keep]


def obstacle_flow(n, foe, a0, box, rng, noise=0.0):
    """``n`` normal-flow events on a surface facing the camera that stands on the road at row
    ``foot`` below the FOE (one depth: 1/tau = a0 foot), in columns |dx| < ``half_width`` and
    rows ``lo`` < dy < ``foot`` (``box = (foot, half_width, lo)``); 80 % of the edges
    horizontal (a car's bumper, sills and shadow), the rest vertical. Returns x, y, nx, ny, s."""
    foot, hw, lo = box
    x = np.floor(foe[0] + rng.uniform(-hw, hw, n)) + 0.5
    y = np.floor(foe[1] + rng.uniform(lo, foot, n)) + 0.5
    ang = np.where(rng.random(n) < 0.8, np.pi / 2, 0.0) + rng.normal(0, 0.1, n)
    nx, ny = np.cos(ang), np.sin(ang)
    dn = (x - foe[0]) * nx + (y - foe[1]) * ny
    flip = dn < 0
    nx[flip], ny[flip], dn[flip] = -nx[flip], -ny[flip], -dn[flip]
    s = a0 * foot * dn * (1 + noise * rng.standard_normal(n))
    keep = s > 1e-3
    return x[keep], y[keep], nx[keep], ny[keep], s[keep]


def rotating_planar_flow(n, foe, a, om, T, slab_us, f, rng, width=320, height=240, noise=0.0,
                         outliers=0.0, duration_us=None):
    """``n`` normal-flow events of the road and facades of :func:`planar_flow` seen by a camera
    that also turns: at ``Om = om[k]`` px/s (``f w``) in slab k before T (the times, in the
    last ``duration_us``, default all slabs, are integers, uniform). The planes, the FOE and
    the scales are those of the camera frame at T; an event at time t is seen from the frame
    turned by the pitch between T and t (:func:`pitch_back`), its translational flow mapped
    accordingly, plus the rotational flow of its slab. Returns x, y, nx, ny, s (float64) and
    t (int64), in time order."""
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    om = np.asarray(om, np.float64)
    dur = len(om) * slab_us if duration_us is None else duration_us
    t = np.sort(rng.integers(T - dur, T, n)).astype(np.int64)
    xp, yp = rng.uniform(0, width - 1, n), rng.uniform(0, height - 1, n)  # in T's frame
    dxx, dyy = xp - foe[0], yp - foe[1]
    g_road = np.where(dyy > 0, a[0] * dyy, 0.0)
    g_fac = np.where(dxx < 0, a[1] * -dxx, a[2] * dxx)
    g = np.maximum(g_road, g_fac)
    b = pitch_back(t, T, slab_us, om, f)
    zero = np.zeros(n)
    x, y, _, _ = warp(xp, yp, zero, zero, -b, f, cx, cy)  # the event's own frame
    X, Y = (x - cx) / f, (y - cy) / f
    sb, cb = np.sin(b), np.cos(b)
    D = sb * Y + cb
    # v_own = J^-1 v' with J = d(warp by b)/d(own position) = [[1/D, -X sb/D^2], [0, 1/D^2]]
    vpx, vpy = g * dxx, g * dyy
    vy_own = vpy * D ** 2
    vx_own = D * (vpx + X * sb / D ** 2 * vy_own)
    k = slab_of(t, T, slab_us)
    w = om[k]
    vx_own += X * Y * w[:, 0] - (1 + X * X) * w[:, 1] + Y * w[:, 2]
    vy_own += (1 + Y * Y) * w[:, 0] - X * Y * w[:, 1] - X * w[:, 2]
    ang = rng.uniform(0, 2 * np.pi, n)
    nx, ny = np.cos(ang), np.sin(ang)
    s = nx * vx_own + ny * vy_own
    flip = s < 0
    nx[flip], ny[flip], s[flip] = -nx[flip], -ny[flip], -s[flip]
    s = s * (1 + noise * rng.standard_normal(n))
    bad = rng.random(n) < outliers
    s[bad] = rng.uniform(1, 200, bad.sum())
    keep = s > 1e-3
    return x[keep], y[keep], nx[keep], ny[keep], s[keep], t[keep]
