"""Least-squares pieces of the flow kernels (``lk_flow``, ``plane_flow``).

* 2x2 symmetric systems: the normal equations of a fit with two unknowns (a plane's two slopes,
  or a flow vector), ``[[a00, a01], [a01, a11]] x = b``: determinant, Cramer's rule and the two
  eigenvalues (the structure tensor's test of ``lk_flow``). Both kernels solve with these;
* the least-squares plane through points: :func:`centred_moments` (two passes: means, then
  centred sums) feeds both plane fits of ``plane_flow``; :func:`plane_fit_raw` is ``lk_flow``'s
  (one pass over raw sums, corrected by 1 / n). The two give the same plane in exact arithmetic
  but round differently, and their degeneracy tests differ (``plane_flow``: both variances
  positive and det > 1e-9 cxx cyy; ``lk_flow``: det > 1e-9 (cuu cww + 1e-300)), so each kernel
  keeps its own, bit for bit;
* the unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (cyclic Jacobi): the
  normal of a total-least-squares plane.

All functions use numba's default error model, like the kernels that call them (a division by
zero raises).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# two smallest eigenvalues closer than this (relative to the largest): normal undefined.
EIG_EPS = 1e-12


@njit(cache=True, inline="always")
def sym2_det(a00, a01, a11):
    """Determinant of the symmetric matrix [[a00, a01], [a01, a11]]."""
    return a00 * a11 - a01 * a01


@njit(cache=True, inline="always")
def sym2_solve(a00, a01, a11, b0, b1, det):
    """Solution (x0, x1) of [[a00, a01], [a01, a11]] x = (b0, b1) by Cramer's rule, ``det`` the
    matrix's determinant (:func:`sym2_det`, checked by the caller)."""
    return (a11 * b0 - a01 * b1) / det, (a00 * b1 - a01 * b0) / det


@njit(cache=True, inline="always")
def sym2_eigenvalues(a00, a01, a11):
    """Eigenvalues (lambda1 >= lambda2) of the symmetric matrix [[a00, a01], [a01, a11]]."""
    pp = a00 + a11
    disc = np.sqrt((a00 - a11) * (a00 - a11) + 4.0 * a01 * a01)
    return 0.5 * (pp + disc), 0.5 * (pp - disc)


@njit(cache=True, inline="always")
def centred_moments(X, Y, T, use, n):
    """Means and centred second moments of the points ``i < n`` with ``use[i]``.

    Returns (m, mx, my, mt, cxx, cyy, ctt, cxy, cxt, cyt): the number of points, the means and
    the sums of products of the deviations from them (not divided by m); all 0 when m < 3."""
    m = 0
    sx = 0.0
    sy = 0.0
    st = 0.0
    for i in range(n):
        if use[i]:
            m += 1
            sx += X[i]
            sy += Y[i]
            st += T[i]
    if m < 3:
        return m, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    mx = sx / m
    my = sy / m
    mt = st / m
    cxx = 0.0
    cyy = 0.0
    ctt = 0.0
    cxy = 0.0
    cxt = 0.0
    cyt = 0.0
    for i in range(n):
        if use[i]:
            dx = X[i] - mx
            dy = Y[i] - my
            dt = T[i] - mt
            cxx += dx * dx
            cyy += dy * dy
            ctt += dt * dt
            cxy += dx * dy
            cxt += dx * dt
            cyt += dy * dt
    return m, mx, my, mt, cxx, cyy, ctt, cxy, cxt, cyt


@njit(cache=True)
def plane_fit_raw(U, W, FV, keep, m):
    """Least-squares plane F = c + gx u + gy w over the points ``q < m`` with ``keep[q]``
    (``lk_flow``). Returns (c, gx, gy, ok); not ok with fewer than three points or a collinear
    support.

    One pass over raw sums, corrected by 1 / n (:func:`centred_moments` gives the same plane
    with other roundings)."""
    s1 = 0.0
    su = 0.0
    sw = 0.0
    suu = 0.0
    sww = 0.0
    suw = 0.0
    sf = 0.0
    suf = 0.0
    swf = 0.0
    for q in range(m):
        if keep[q]:
            u = U[q]
            w = W[q]
            f = FV[q]
            s1 += 1.0
            su += u
            sw += w
            suu += u * u
            sww += w * w
            suw += u * w
            sf += f
            suf += u * f
            swf += w * f
    if s1 < 3.0:
        return 0.0, 0.0, 0.0, False
    cuu = suu - su * su / s1
    cww = sww - sw * sw / s1
    cuw = suw - su * sw / s1
    cuf = suf - su * sf / s1
    cwf = swf - sw * sf / s1
    det = sym2_det(cuu, cuw, cww)
    if det <= 1e-9 * (cuu * cww + 1e-300):
        return 0.0, 0.0, 0.0, False  # collinear support: no plane
    gx, gy = sym2_solve(cuu, cuw, cww, cuf, cwf, det)
    c = (sf - gx * su - gy * sw) / s1
    return c, gx, gy, True


@njit(cache=True, inline="always")
def _jacobi_sweep(A, V):
    """One cyclic Jacobi sweep over the off-diagonal entries (0, 1), (0, 2), (1, 2) of the
    symmetric 3x3 ``A`` (in place), accumulating the rotations in ``V``."""
    for p in range(2):
        for q in range(p + 1, 3):
            apq = A[p, q]
            if apq == 0.0:
                continue
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            tt = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                tt = -tt
            c = 1.0 / math.sqrt(tt * tt + 1.0)
            s = tt * c
            for k in range(3):  # A <- A J (columns p, q)
                akp = A[k, p]
                akq = A[k, q]
                A[k, p] = c * akp - s * akq
                A[k, q] = s * akp + c * akq
            for k in range(3):  # A <- J^T A (rows p, q)
                apk = A[p, k]
                aqk = A[q, k]
                A[p, k] = c * apk - s * aqk
                A[q, k] = s * apk + c * aqk
            for k in range(3):
                vkp = V[k, p]
                vkq = V[k, q]
                V[k, p] = c * vkp - s * vkq
                V[k, q] = s * vkp + c * vkq


@njit(cache=True, inline="always")
def _smallest_diagonal(A):
    """Index of the smallest diagonal entry of the diagonalised ``A``, and whether it is
    separated from the next one by more than :data:`EIG_EPS` times the largest magnitude."""
    e0 = A[0, 0]
    e1 = A[1, 1]
    e2 = A[2, 2]
    j = 0
    if e1 < e0 and e1 <= e2:
        j = 1
    elif e2 < e0 and e2 < e1:
        j = 2
    lo = A[j, j]
    nxt = np.inf
    big = -np.inf
    for k in range(3):
        if k != j:
            nxt = min(nxt, A[k, k])
        big = max(big, abs(A[k, k]))
    return j, not (nxt - lo <= EIG_EPS * big)


@njit(cache=True)
def smallest_eigvec3(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (cyclic Jacobi).

    Jacobi rotations give eigenvalues to about eps * |A| absolutely, so a small eigenvalue stays
    separable from its neighbour even when one eigenvalue dominates (a closed-form cubic solver
    loses ~sqrt(eps) there). Returns (ok, v0, v1, v2) with v2 >= 0; not ok when the smallest
    eigenvalue is (numerically) repeated.
    """
    A = np.empty((3, 3))
    A[0, 0] = a00
    A[0, 1] = a01
    A[0, 2] = a02
    A[1, 0] = a01
    A[1, 1] = a11
    A[1, 2] = a12
    A[2, 0] = a02
    A[2, 1] = a12
    A[2, 2] = a22
    V = np.eye(3)
    scale = a00 * a00 + a11 * a11 + a22 * a22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    if scale <= 0.0:
        return False, 0.0, 0.0, 0.0
    for _ in range(30):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        if off <= 1e-34 * scale:
            break
        _jacobi_sweep(A, V)
    j, separated = _smallest_diagonal(A)
    if not separated:
        return False, 0.0, 0.0, 0.0
    v0 = V[0, j]
    v1 = V[1, j]
    v2 = V[2, j]
    nn = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    v0 /= nn
    v1 /= nn
    v2 /= nn
    if v2 < 0.0:  # sign convention: normal with n_t >= 0
        v0, v1, v2 = -v0, -v1, -v2
    return True, v0, v1, v2
