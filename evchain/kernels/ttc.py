"""Numba kernels of ``ttc``: per-event time to contact in region B, clustering, per-cluster fusion.

Cluster state ``C[k, :]`` (float64) has the columns below; ``I[k, :]`` (int64) holds id, active
flag, number of stored samples and ring position. Each cluster keeps a ring of its recent samples
``(t_us, tau_s)`` in ``ST[k]``, ``SV[k]``. ``G`` (float64) holds the carried state: ``[0]`` 1 when
an FOE is known, ``[1]`` foe x, ``[2]`` foe y, ``[3]`` next tick (µs), ``[4]`` next cluster id.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

CX, CY, SIZE, ACT, TLAST, TAU, VAR, HAS, MISS, TTAU = range(10)
NCOL = 10
ID, ACTIVE, NS, POS = range(4)


@njit(cache=True)
def event_tau(px, py, vx, vy, fx, fy, half_width, min_below, min_dist, min_speed, max_speed,
              min_tau, max_tau):
    """tau = (p - foe).v / |v|^2 for a flow event in region B, or -1 when it does not qualify.

    Region B: below the FOE by at least ``min_below`` px, ``|x - fx| <= half_width``, at least
    ``min_dist`` px from the FOE, diverging, speed in [min_speed, max_speed], tau in
    [min_tau, max_tau].
    """
    rx = px - fx
    ry = py - fy
    if ry < min_below or abs(rx) > half_width:
        return -1.0
    if rx * rx + ry * ry < min_dist * min_dist:
        return -1.0
    s2 = vx * vx + vy * vy
    if not (s2 > 0.0) or s2 < min_speed * min_speed or s2 > max_speed * max_speed:
        return -1.0
    d = rx * vx + ry * vy
    if not (d > 0.0):
        return -1.0
    tau = d / s2
    if tau < min_tau or tau > max_tau:
        return -1.0
    return tau


@njit(cache=True)
def _cluster_estimate(C, I, ST, SV, k, T, max_age_us, min_samples, rel_floor, q_s2_per_s,
                      gate, buf):
    """Update cluster k's fused tau at tick time T from its recent samples (median, MAD)."""
    n = 0
    nb = I[k, NS]
    for j in range(nb):
        age = T - ST[k, j]
        if age <= max_age_us:
            buf[n] = SV[k, j] - age * 1e-6
            n += 1
    has = C[k, HAS] > 0.0
    if has:  # predict: tau falls 1 s per s
        dt = (T - C[k, TTAU]) * 1e-6
        C[k, TAU] -= dt
        C[k, VAR] += q_s2_per_s * dt
        C[k, TTAU] = T
    if n < min_samples:
        return
    vals = np.sort(buf[:n])
    if n % 2 == 1:
        med = vals[n // 2]
    else:
        med = 0.5 * (vals[n // 2 - 1] + vals[n // 2])
    for j in range(n):
        vals[j] = abs(vals[j] - med)
    vals = np.sort(vals)
    mad = vals[n // 2] if n % 2 == 1 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])
    sigma = 1.4826 * mad / math.sqrt(n) + rel_floor * abs(med)
    r = sigma * sigma + 1e-12
    if not has:
        C[k, TAU] = med
        C[k, VAR] = r
        C[k, HAS] = 1.0
        C[k, TTAU] = T
        C[k, MISS] = 0.0
        return
    innov = med - C[k, TAU]
    s = C[k, VAR] + r
    if innov * innov > gate * gate * s:
        C[k, MISS] += 1.0
        if C[k, MISS] >= 3.0:  # the measurements insist: restart from them
            C[k, TAU] = med
            C[k, VAR] = r
            C[k, MISS] = 0.0
        return
    C[k, MISS] = 0.0
    gain = C[k, VAR] / s
    C[k, TAU] += gain * innov
    C[k, VAR] = (1.0 - gain) * C[k, VAR]


@njit(cache=True)
def process(x, y, t, vx, vy, ft, fx, fy, C, I, ST, SV, G, t_end, period_us, select_nearest,
            select_min_activity,
            half_width, min_below, min_dist, min_speed, max_speed, min_tau, max_tau,
            init_size, max_size, join_margin, act_tau_us, min_activity,
            max_age_us, min_samples, rel_floor, q_s2_per_s, gate,
            o_t, o_tau, o_id, o_x, o_y, o_sup, c_t, c_id, c_x, c_y, c_size, c_tau, c_sup):
    """Process one packet; returns (number of obstacle rows, number of cluster rows).

    Ticks at multiples of ``period_us`` see the events before them (cut-independent). FOE
    entries ``ft`` apply to the events at or after their time.
    """
    K = C.shape[0]
    B = ST.shape[1]
    buf = np.empty(B, np.float64)
    n = t.shape[0]
    nf = ft.shape[0]
    j = 0
    i = 0
    no = 0
    nc = 0
    while True:
        t_next = t[i] if i < n else t_end
        while G[3] < t_next or (i < n and G[3] == t_next):
            T = G[3]
            best = -1
            best_sup = 0.0
            best_d = 1e300
            for k in range(K):
                if I[k, ACTIVE] == 0:
                    continue
                a = C[k, ACT] * math.exp(-(T - C[k, TLAST]) / act_tau_us)
                if a < min_activity:
                    I[k, ACTIVE] = 0
                    continue
                _cluster_estimate(C, I, ST, SV, k, T, max_age_us, min_samples, rel_floor,
                                  q_s2_per_s, gate, buf)
                if C[k, HAS] > 0.0 and C[k, TAU] <= 0.0:  # passed or hit: drop it
                    I[k, ACTIVE] = 0
                    continue
                if C[k, HAS] > 0.0 and nc < c_t.shape[0]:
                    c_t[nc] = T
                    c_id[nc] = I[k, ID]
                    c_x[nc] = C[k, CX]
                    c_y[nc] = C[k, CY]
                    c_size[nc] = C[k, SIZE]
                    c_tau[nc] = C[k, TAU]
                    c_sup[nc] = a
                    nc += 1
                    if select_nearest:
                        # the supported cluster nearest the FOE (its square's nearest point):
                        # the first thing in the driving corridor; ties by support
                        if a >= select_min_activity:
                            ddx = max(0.0, abs(C[k, CX] - G[1]) - C[k, SIZE])
                            ddy = max(0.0, abs(C[k, CY] - G[2]) - C[k, SIZE])
                            d = math.sqrt(ddx * ddx + ddy * ddy)
                            if d < best_d or (d == best_d and a > best_sup):
                                best_d = d
                                best_sup = a
                                best = k
                    elif a > best_sup:
                        best_sup = a
                        best = k
            if best >= 0 and no < o_t.shape[0]:
                o_t[no] = T
                o_tau[no] = C[best, TAU]
                o_id[no] = I[best, ID]
                o_x[no] = C[best, CX]
                o_y[no] = C[best, CY]
                o_sup[no] = best_sup
                no += 1
            G[3] = T + period_us
        if i >= n:
            break
        ti = t[i]
        while j < nf and ft[j] <= ti:
            if fx[j] == fx[j] and fy[j] == fy[j]:
                G[0] = 1.0
                G[1] = fx[j]
                G[2] = fy[j]
            j += 1
        if G[0] > 0.0:
            px = float(x[i])
            py = float(y[i])
            tau = event_tau(px, py, np.float64(vx[i]), np.float64(vy[i]), G[1], G[2], half_width,
                            min_below, min_dist, min_speed, max_speed, min_tau, max_tau)
            if tau > 0.0:
                # nearest cluster (inf-norm) whose square, widened by the margin, holds p
                kb = -1
                db = 1e300
                free = -1
                weakest = -1
                wa = 1e300
                for k in range(K):
                    if I[k, ACTIVE] == 0:
                        if free < 0:
                            free = k
                        continue
                    a = C[k, ACT] * math.exp(-(ti - C[k, TLAST]) / act_tau_us)
                    if a < min_activity and free < 0:
                        free = k
                    if a < wa:
                        wa = a
                        weakest = k
                    d = max(abs(px - C[k, CX]), abs(py - C[k, CY]))
                    if d <= C[k, SIZE] + join_margin and d < db:
                        db = d
                        kb = k
                if kb < 0:
                    kb = free if free >= 0 else weakest
                    I[kb, ID] = int(G[4])
                    G[4] += 1.0
                    I[kb, ACTIVE] = 1
                    I[kb, NS] = 0
                    I[kb, POS] = 0
                    C[kb, CX] = px
                    C[kb, CY] = py
                    C[kb, SIZE] = init_size
                    C[kb, ACT] = 1.0
                    C[kb, TLAST] = ti
                    C[kb, HAS] = 0.0
                    C[kb, MISS] = 0.0
                    C[kb, TAU] = 0.0
                    C[kb, VAR] = 0.0
                    C[kb, TTAU] = ti
                else:
                    a = C[kb, ACT] * math.exp(-(ti - C[kb, TLAST]) / act_tau_us) + 1.0
                    C[kb, ACT] = a
                    C[kb, TLAST] = ti
                    # grow towards events near or beyond the boundary, then move the centre
                    if db > C[kb, SIZE]:
                        C[kb, SIZE] = min(max_size, db)
                    C[kb, CX] += (px - C[kb, CX]) / a
                    C[kb, CY] += (py - C[kb, CY]) / a
                p = I[kb, POS]
                ST[kb, p] = ti
                SV[kb, p] = tau
                I[kb, POS] = (p + 1) % B
                if I[kb, NS] < B:
                    I[kb, NS] += 1
        i += 1
    while j < nf:  # FOE entries after the last event still count for the next packet
        if fx[j] == fx[j] and fy[j] == fy[j]:
            G[0] = 1.0
            G[1] = fx[j]
            G[2] = fy[j]
        j += 1
    return no, nc
