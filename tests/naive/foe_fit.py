"""Plain numpy reference of the ``foe_fit`` kernel, and a piecewise-planar flow generator."""

from __future__ import annotations

import numpy as np


def _geometry(x, y, nx, ny, th, margin):
    dxx, dyy = x - th[0], y - th[1]
    dn = dxx * nx + dyy * ny
    lev = np.stack([dyy, -dxx, dxx], 1)  # the planes' factors d: road, left, right
    app = (lev > margin) & (dn > 0)[:, None]
    return dxx, dyy, dn, lev, app


def fit(x, y, nx, ny, s, t, T, tau_us, th, margin, c, max_iter, max_step):
    """Same contract as ``evchain.kernels.foe_fit.fit`` on all given events (th is copied)."""
    th = np.array(th, np.float64)
    wt = np.exp(-(T - t) / tau_us)

    dxx, dyy, dn, lev, app = _geometry(x, y, nx, ny, th, margin)
    for k in range(3):
        ini = app[:, k] & ((dyy < -margin) if k else True)  # facades: above the FOE's row
        if np.isnan(th[2 + k]) and ini.any():
            r = s[ini] / (dn * lev[:, k])[ini]
            w = wt[ini]
            o = np.argsort(r, kind="quicksort")
            th[2 + k] = r[o][np.argmax(np.cumsum(w[o]) >= 0.5 * w.sum())]
    inl = tot = 0.0
    for _ in range(max_iter):
        A, b, inl, tot = normal_equations(x, y, nx, ny, s, wt, th, margin, c)
        tr = np.trace(A)
        if not tr > 0:
            return False, th, inl, tot
        for p in range(5):
            if A[p, p] <= 1e-12 * tr:
                A[p, :] = 0.0
                A[:, p] = 0.0
                A[p, p] = 1.0
                b[p] = 0.0
            else:
                A[p, p] += 1e-9 * tr
        try:
            d = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            return False, th, inl, tot
        step = max(abs(d[0]), abs(d[1]))
        d[:2] *= 1.0 if step <= max_step else max_step / step
        th = th + d
        if not np.isfinite(th[:2]).all() or np.isinf(th[2:]).any():
            return False, th, inl, tot
        if step < 0.05:  # px, as the kernel
            break
    return True, th, inl, tot


def normal_equations(x, y, nx, ny, s, wt, th, margin, c):
    """One Gauss-Newton pass at ``th`` with decay weights ``wt``: (J^T W J, J^T W r, inlier
    weight, applicable weight); the kernel's ``_sums`` holds the same numbers."""
    dxx, dyy, dn, lev, app = _geometry(x, y, nx, ny, th, margin)
    app &= ~np.isnan(th[2:])[None, :]
    pred = np.where(app, th[2:][None, :] * dn[:, None] * lev, np.nan)
    res = np.where(app, np.abs(s[:, None] - pred), np.inf)
    k = np.argmin(res, 1)  # the plane predicting the speed best (road wins ties)
    idx = np.arange(len(s))
    pk = pred[idx, k]
    use = np.isfinite(res[idx, k]) & (pk > 0)
    u = np.where(use, res[idx, k] / np.where(use, pk, 1.0) / c, np.inf)
    tot = wt[use].sum()
    inlier = use & (u < 1)
    inl = wt[inlier].sum()
    w = np.where(inlier, wt * (1 - u * u) ** 2 / np.where(inlier, pk, 1.0) ** 2, 0.0)
    a = th[2 + k]
    J = np.zeros((len(s), 5))
    m0, m1, m2 = inlier & (k == 0), inlier & (k == 1), inlier & (k == 2)
    J[m0, 0] = (-a * nx * dyy)[m0]
    J[m0, 1] = (-a * (ny * dyy + dn))[m0]
    J[m1, 0] = (a * (nx * dxx + dn))[m1]
    J[m1, 1] = (a * ny * dxx)[m1]
    J[m2, 0] = (-a * (nx * dxx + dn))[m2]
    J[m2, 1] = (-a * ny * dxx)[m2]
    J[inlier, 2 + k[inlier]] = (dn * lev[idx, k])[inlier]
    r = np.where(inlier, s - pred[idx, k], 0.0)
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
