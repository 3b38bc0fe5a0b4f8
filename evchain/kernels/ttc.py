"""Numba kernels of ``ttc``: per-event time to contact in region B, clustering, per-cluster fusion.

Cluster state ``C[k, :]`` (float64) has the columns below; ``I[k, :]`` (int64) holds id, active
flag, number of stored samples and ring position. Each cluster keeps a ring of its recent samples
``(t_us, tau_s)`` in ``ST[k]``, ``SV[k]``. ``G`` (float64) holds the carried state: ``[0]`` 1 when
an FOE is known, ``[1]`` foe x, ``[2]`` foe y, ``[3]`` next tick (µs), ``[4]`` next cluster id,
``[5]`` the ground constant K (s px), ``[6]`` the number of votes for K, ``[7]`` the id of the
last selected cluster (-1: none), ``[8]`` the reference time of the votes' weights (µs).

Ground plane: for a road point at ``dy = y - y_foe`` rows below the FOE, seen by a level camera
at height h moving at speed V, ``tau * dy = f h / V =: K`` (the same for all road points). An
obstacle point at height hp above the road has ``tau * dy = K (1 - hp / h) < K``: it is nearer
than the road at its row. K is estimated from the events themselves: the mode of ``tau * dy``
over region-B events (a fading histogram ``H`` of its log, see ``ground_vote``,
``ground_mode``; events joining a cluster already known to be off the road are left out);
each cluster keeps ``tau * dy`` of its samples in ``SK[k]`` and its
ratio ``rho = median(tau * dy) / K`` in ``C[k, RHO]``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

CX, CY, SIZE, ACT, TLAST, TAU, VAR, HAS, MISS, TTAU, RHO = range(11)
NCOL = 11
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
def baseline_tau(S, pol, px, py, nx, ny, d0, ti, max_px, max_age_us):
    """tau from where the edge through (px, py) was earlier, or -1 when nothing qualifies.

    ``S[pol]`` holds each pixel's last flow-event time (µs). Walking back from p against the
    unit normal n (away from the FOE, ``d0 = (p - foe).n``) by 1..``max_px`` px (nearest
    pixels), the times must fall strictly and stay within ``max_age_us`` of ``ti``. For the
    farthest such pixel q (``dd = (p - q).n`` px earlier, at time tq) an edge approaching at
    constant speed has ``d(t) = D / (t_c - t)``, so ``tau = (d0 - dd) (ti - tq) / dd``: positions
    and times only, over a baseline as long as the edge took, no flow magnitude.
    """
    h = S.shape[1]
    w = S.shape[2]
    ix = int(math.floor(px + 0.5))
    iy = int(math.floor(py + 0.5))
    tprev = ti
    tau = -1.0
    for k in range(1, max_px + 1):
        qx = int(math.floor(px - k * nx + 0.5))
        qy = int(math.floor(py - k * ny + 0.5))
        if qx < 0 or qy < 0 or qx >= w or qy >= h:
            break
        if qx == ix and qy == iy:
            continue
        tq = S[pol, qy, qx]
        if not (tq < tprev) or ti - tq > max_age_us:
            break
        dd = (px - qx) * nx + (py - qy) * ny
        dk = d0 - dd
        if not (dd > 0.0) or not (dk > 0.0):
            break
        tau = dk * (ti - tq) * 1e-6 / dd
        tprev = tq
    return tau


KG_LN_MIN = math.log(0.01)  # ground histogram: bins of ln(tau * dy) from 0.01 s px
KG_BIN = 0.02               # bin width in ln (2 %)
KG_BINS = 1024              # up to 0.01 e^20.48 ~ 8e6 s px


@njit(cache=True)
def ground_vote(H, G, kg, t_us, memory_us):
    """Add kg = tau * dy > 0 of an event at ``t_us`` to the ground histogram ``H`` (bins of
    ln kg), weighted ``exp((t_us - G[8]) / memory_us)`` (older votes fade with that memory);
    ``G[6]`` counts the votes, ``G[8]`` is the weights' reference time (the first vote's, moved
    on with a rescale before the weights overflow)."""
    if not (kg > 0.0):
        return
    b = int(math.floor((math.log(kg) - KG_LN_MIN) / KG_BIN))
    if b < 0 or b >= H.shape[0]:
        return
    if G[6] == 0.0:
        G[8] = t_us
    w = math.exp((t_us - G[8]) / memory_us)
    if w > 1e100:
        for j in range(H.shape[0]):
            H[j] /= w
        G[8] = t_us
        w = 1.0
    H[b] += w
    G[6] += 1.0


@njit(cache=True)
def ground_mode(H, half_bins):
    """The ground constant K: the road's mode of tau * dy, the weighted mean of ln kg over the
    window of ``2 half_bins + 1`` bins holding the most weight (first of equals); 0 if empty."""
    nb = H.shape[0]
    w = 2 * half_bins + 1
    best, best_s = 0, -1.0
    for j in range(max(1, nb - w + 1)):
        s = 0.0
        for i in range(j, min(j + w, nb)):
            s += H[i]
        if s > best_s:
            best, best_s = j, s
    tot = 0.0
    m = 0.0
    for j in range(best, min(best + w, nb)):
        tot += H[j]
        m += H[j] * (j + 0.5)
    if not (tot > 0.0):
        return 0.0
    return math.exp(KG_LN_MIN + KG_BIN * m / tot)


@njit(cache=True)
def _median_sorted(vals, n):
    return vals[n // 2] if n % 2 == 1 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])


@njit(cache=True)
def _cluster_estimate(C, I, ST, SV, SK, k, T, max_age_us, min_samples, rel_floor, q_s2_per_s,
                      gate, k_ground, buf):
    """Update cluster k's fused tau at tick time T from its recent samples (median, MAD), and
    its ground ratio rho (median of tau * dy over K; left as it is while K is unknown)."""
    n = 0
    nb = I[k, NS]
    for j in range(nb):
        age = T - ST[k, j]
        if age <= max_age_us:
            buf[n] = SK[k, j]
            n += 1
    if n >= min_samples and k_ground > 0.0:
        C[k, RHO] = _median_sorted(np.sort(buf[:n]), n) / k_ground
    n = 0
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
    med = _median_sorted(vals, n)
    for j in range(n):
        vals[j] = abs(vals[j] - med)
    vals = np.sort(vals)
    mad = _median_sorted(vals, n)
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
def process(x, y, t, pol, vx, vy, ft, fx, fy, C, I, ST, SV, SK, G, S, H, t_end, period_us,
            select_nearest, select_min_activity,
            half_width, min_below, min_dist, min_speed, max_speed, min_tau, max_tau,
            init_size, max_size, join_margin, act_tau_us, min_activity,
            max_age_us, min_samples, rel_floor, q_s2_per_s, gate,
            ground_test, ground_tol, ground_memory_us, ground_min_events, ground_fallback,
            corridor, hold, base_px, base_age_us,
            o_t, o_tau, o_id, o_x, o_y, o_sup, c_t, c_id, c_x, c_y, c_size, c_tau, c_sup,
            c_rho):
    """Process one packet; returns (number of obstacle rows, number of cluster rows).

    Ticks at multiples of ``period_us`` see the events before them (cut-independent). FOE
    entries ``ft`` apply to the events at or after their time. With ``ground_test`` only
    clusters with rho < 1 - ground_tol (nearer than the road at their rows) can be the
    obstacle once K has seen ``ground_min_events`` events; when there is none,
    ``ground_fallback`` selects among all clusters, else the tick has no obstacle row. With
    ``corridor`` > 0 a cluster must reach into the driving corridor: the lateral gap between
    its square and the FOE at most ``corridor`` times the depth of its lower edge below the FOE
    (a road point at (dx, dy) below the FOE lies dx / dy camera heights to the side). With
    ``hold`` the previous tick's obstacle (id in ``G[7]``) stays selected while it qualifies.
    """
    K = C.shape[0]
    B = ST.shape[1]
    half_bins = int(round(math.log(1.0 + ground_tol) / KG_BIN))
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
            if G[6] >= ground_min_events:
                G[5] = ground_mode(H, half_bins)
            k_ground = G[5] if G[6] >= ground_min_events else 0.0
            use_ground = ground_test and k_ground > 0.0
            best = -1
            best_sup = 0.0
            best_d = 1e300
            held = -1
            fb = -1  # the fallback choice (ground test ignored)
            fb_sup = 0.0
            fb_d = 1e300
            for k in range(K):
                if I[k, ACTIVE] == 0:
                    continue
                a = C[k, ACT] * math.exp(-(T - C[k, TLAST]) / act_tau_us)
                if a < min_activity:
                    I[k, ACTIVE] = 0
                    continue
                _cluster_estimate(C, I, ST, SV, SK, k, T, max_age_us, min_samples, rel_floor,
                                  q_s2_per_s, gate, k_ground, buf)
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
                    rho = C[k, RHO]
                    c_rho[nc] = rho if (k_ground > 0.0 and rho == rho) else -1.0
                    nc += 1
                    if select_nearest and a < select_min_activity:
                        continue
                    if corridor > 0.0:
                        gap = max(0.0, abs(C[k, CX] - G[1]) - C[k, SIZE])
                        if gap > corridor * (C[k, CY] + C[k, SIZE] - G[2]):
                            continue  # beside the driving corridor
                    # nearest the FOE (its square's nearest point; the first thing in the
                    # driving corridor; ties by support), or the most active
                    d = 0.0
                    if select_nearest:
                        ddx = max(0.0, abs(C[k, CX] - G[1]) - C[k, SIZE])
                        ddy = max(0.0, abs(C[k, CY] - G[2]) - C[k, SIZE])
                        d = math.sqrt(ddx * ddx + ddy * ddy)
                    if d < fb_d or (d == fb_d and a > fb_sup):
                        fb_d = d
                        fb_sup = a
                        fb = k
                    if use_ground and not (C[k, RHO] < 1.0 - ground_tol):
                        continue  # lies on the road (or its rho is not known yet)
                    if hold and I[k, ID] == G[7]:
                        held = k
                    if d < best_d or (d == best_d and a > best_sup):
                        best_d = d
                        best_sup = a
                        best = k
            if held >= 0:
                best = held
                best_sup = C[held, ACT] * math.exp(-(T - C[held, TLAST]) / act_tau_us)
            if best < 0 and (ground_fallback or not use_ground):
                best = fb
                best_sup = fb_sup
            G[7] = I[best, ID] if best >= 0 else -1.0
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
            evx = np.float64(vx[i])
            evy = np.float64(vy[i])
            tau = event_tau(px, py, evx, evy, G[1], G[2], half_width,
                            min_below, min_dist, min_speed, max_speed, min_tau, max_tau)
            if tau > 0.0 and base_px > 0:
                sp = math.sqrt(evx * evx + evy * evy)
                tau = baseline_tau(S, 1 if pol[i] > 0 else 0, px, py, evx / sp, evy / sp,
                                   tau * sp, float(ti), base_px, base_age_us)
                if tau < min_tau or tau > max_tau:
                    tau = -1.0
            if tau > 0.0:
                kg = tau * (py - G[2])
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
                    C[kb, RHO] = math.nan
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
                SK[kb, p] = kg
                I[kb, POS] = (p + 1) % B
                if I[kb, NS] < B:
                    I[kb, NS] += 1
                # K learns from events of clusters not (yet) known to be off the road
                if not (C[kb, RHO] < 1.0 - ground_tol):
                    ground_vote(H, G, kg, float(ti), ground_memory_us)
        if S.shape[1] > 0:
            qx = int(x[i])
            qy = int(y[i])
            if 0 <= qx < S.shape[2] and 0 <= qy < S.shape[1]:
                S[1 if pol[i] > 0 else 0, qy, qx] = ti
        i += 1
    while j < nf:  # FOE entries after the last event still count for the next packet
        if fx[j] == fx[j] and fy[j] == fy[j]:
            G[0] = 1.0
            G[1] = fx[j]
            G[2] = fy[j]
        j += 1
    return no, nc
