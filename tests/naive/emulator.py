"""Slow, obvious reference of the DVS emulator (no noise): plain Python per pixel.

Same rule as ``evchain.kernels.emulator``: L = ln(I + eps) in float64 of the float32 input;
reference L_ref = l0 + (n_on*c_on - n_off*c_off) from integer counts; an ON event when
L1 >= L_ref + c_on - tol, OFF when L1 <= L_ref - c_off + tol; crossing time from linear or
monotone cubic Hermite interpolation (three-point slopes limited by Fritsch-Carlson); time
rounded to nearest µs; events of an interval ordered by rounded time, then row, column.
"""

from __future__ import annotations

import math

import numpy as np


def _slope3(d1, d2, h1, h2):
    if d1 * d2 <= 0:
        return 0.0
    d = (h2 * d1 + h1 * d2) / (h1 + h2)
    m = 3 * min(abs(d1), abs(d2))
    return max(-m, min(m, d))


def _hermite(s, la, lb, m0, m1):
    return ((2 * s**3 - 3 * s**2 + 1) * la + (s**3 - 2 * s**2 + s) * m0
            + (-2 * s**3 + 3 * s**2) * lb + (s**3 - s**2) * m1)


def _solve(level, la, lb, m0, m1, cubic):
    if lb == la:
        return 0.0
    s = (level - la) / (lb - la)
    if s <= 0:
        return 0.0
    if s >= 1:
        return 1.0
    if not cubic:
        return s
    lo, hi = 0.0, 1.0
    up = lb > la
    for _ in range(200):          # plain bisection
        mid = 0.5 * (lo + hi)
        below = _hermite(mid, la, lb, m0, m1) < level
        if below == up:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def emulate(frames, times, c_on, c_off, eps=1e-3, tol=1e-6, cubic=False, refractory_us=0.0,
            cap=None):
    """frames float32 [n, H, W], times int [n]; c_on/c_off scalars or [H, W].

    Returns (x, y, t_int, t_float, p) of all events (all intervals, no look-ahead lag).
    """
    frames = np.asarray(frames, np.float32)
    n, h, w = frames.shape
    c_on = np.broadcast_to(np.asarray(c_on, np.float64), (h, w))
    c_off = np.broadcast_to(np.asarray(c_off, np.float64), (h, w))
    L = np.log(frames.astype(np.float64) + eps)
    k_on = np.zeros((h, w), np.int64)
    k_off = np.zeros((h, w), np.int64)
    last = np.full((h, w), -1e300)
    out = []
    for j in range(n - 1):
        t0, t1 = float(times[j]), float(times[j + 1])
        dt = t1 - t0
        events = []
        for y in range(h):
            for x in range(w):
                la, lb = L[j, y, x], L[j + 1, y, x]
                base = L[0, y, x]
                m0 = m1 = lb - la
                if cubic:
                    sec = (lb - la) / dt
                    da = db = sec
                    if j >= 1:
                        hp = t0 - times[j - 1]
                        da = _slope3((la - L[j - 1, y, x]) / hp, sec, hp, dt)
                    if j + 2 < n:
                        hn = times[j + 2] - t1
                        db = _slope3(sec, (L[j + 2, y, x] - lb) / hn, dt, hn)
                    m0, m1 = da * dt, db * dt
                count = 0
                while cap is None or count < cap:
                    con, coff = c_on[y, x], c_off[y, x]
                    lev = base + ((k_on[y, x] + 1) * con - k_off[y, x] * coff)
                    if lb >= lev - tol:
                        k_on[y, x] += 1
                        pol = 1
                    else:
                        lev = base + (k_on[y, x] * con - (k_off[y, x] + 1) * coff)
                        if lb <= lev + tol:
                            k_off[y, x] += 1
                            pol = -1
                        else:
                            break
                    count += 1
                    lev = lev - tol if pol > 0 else lev + tol   # where the rule turns true
                    tf = t0 + _solve(lev, la, lb, m0, m1, cubic) * dt
                    if tf - last[y, x] < refractory_us:
                        continue
                    last[y, x] = tf
                    events.append((math.floor(tf + 0.5), y, x, tf, pol))
        events.sort(key=lambda e: e[0])   # stable: generation order (row, column, time)
        out.extend(events)
    if not out:
        z = np.zeros(0)
        return z.astype(np.uint16), z.astype(np.uint16), z.astype(np.int64), z, z.astype(np.int8)
    ti, y, x, tf, p = zip(*out, strict=True)
    return (np.array(x, np.uint16), np.array(y, np.uint16), np.array(ti, np.int64),
            np.array(tf), np.array(p, np.int8))
