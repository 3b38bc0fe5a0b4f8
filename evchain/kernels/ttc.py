"""Numba kernels of ``ttc``: per-event time to contact in region B, clustering, per-cluster fusion.

State (:class:`TtcState`, from :func:`new_state`): the clusters (a structured array of
:data:`CLUSTER_STATE`: id, active flag, ring fill and position, square, activity, fused tau and
its variance, ground ratio), each with a ring of its recent samples (time, tau, tau * dy); the
carried scalars (a one-record array of :data:`CARRY`: the FOE, the next tick, the next cluster
id, the ground constant and its votes, the last selected cluster); each pixel's last flow-event
time (for the baseline tau); the ground histogram; the camera's rotation angle since the first
FOE entry, at each entry (the angular velocities integrated: a baseline spans several of them).
Constants: :class:`TtcParams`.

Ground plane: for a road point at ``dy = y - y_foe`` rows below the FOE, seen by a level camera
at height h moving at speed V, ``tau * dy = f h / V =: K`` (the same for all road points). An
obstacle point at height hp above the road has ``tau * dy = K (1 - hp / h) < K``: it is nearer
than the road at its row. K is estimated from the events themselves: the mode of ``tau * dy``
over region-B events (a fading histogram of its log, see ``ground_vote``, ``ground_mode``;
events joining a cluster already known to be off the road are left out); each cluster keeps
``tau * dy`` of its samples and its ratio ``rho = median(tau * dy) / K`` (over the samples
that agree with its measurement where enough do).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

#: one cluster: identity and ring bookkeeping (int64), then its square (centre, half-size px),
#: decayed activity (events) at ``t_last`` (µs), fused tau (s) with variance (s^2) at ``t_tau``
#: (µs), ``has_tau`` 1 once it has one, consecutive gated ``misses``, ground ratio ``rho``,
#: ``spread``: the relative spread of its samples at its last measurement (1.4826 MAD / |median|),
#: ``t_meas``: the time of the newest sample of that measurement (µs); ``mx``, ``my``: where the
#: samples of that measurement lie that agree with it (:func:`_agreeing_samples`; NaN before)
CLUSTER_STATE = np.dtype([("id", "i8"), ("active", "i8"), ("n_samples", "i8"), ("ring_pos", "i8"),
                          ("cx", "f8"), ("cy", "f8"), ("size", "f8"), ("activity", "f8"),
                          ("t_last", "f8"), ("tau", "f8"), ("var", "f8"), ("has_tau", "f8"),
                          ("misses", "f8"), ("t_tau", "f8"), ("rho", "f8"), ("spread", "f8"),
                          ("t_meas", "f8"), ("mx", "f8"), ("my", "f8")])
#: carried from packet to packet: ``has_foe`` 1 once an FOE is known, at (``foe_x``,
#: ``foe_y``), with the camera's angular velocity (``foe_wx``, ``foe_wy``, ``foe_wz``, rad/s;
#: 0 where not estimated); the next tick (µs) and cluster id; the ground constant K (s px),
#: the number of votes for it and their weights' reference time (µs); the id of the last
#: selected cluster (-1: none); the ticks without an obstacle row, by reason
#: (:data:`NO_TTC_REASONS`); ``no_slot``: the events that would have started a cluster while
#: every slot held a live one; ``n_angles``: the entries of the rotation history,
#: ``measured``: 1 while the latest entry's rotation is measured (the gyro's), not fitted to
#: the flow
CARRY = np.dtype([("has_foe", "f8"), ("foe_x", "f8"), ("foe_y", "f8"), ("foe_wx", "f8"),
                  ("foe_wy", "f8"), ("foe_wz", "f8"), ("next_tick", "f8"),
                  ("next_id", "f8"), ("k_ground", "f8"), ("n_votes", "f8"), ("held_id", "f8"),
                  ("votes_t_ref", "f8"), ("no_foe", "f8"), ("no_cluster", "f8"),
                  ("not_credible", "f8"), ("on_road", "f8"), ("no_slot", "f8"),
                  ("n_angles", "f8"), ("measured", "f8")])
#: the fields of :data:`CARRY` counting ticks without a TTC: no FOE yet; no cluster with a tau
#: active enough (and in the corridor); no credible one (:func:`_credible`); only clusters on the
#: road (ground test without fallback)
NO_TTC_REASONS = ("no_foe", "no_cluster", "not_credible", "on_road")

KG_LN_MIN = math.log(0.01)  # ground histogram: bins of ln(tau * dy) from 0.01 s px
KG_BIN = 0.02               # bin width in ln (2 %)
KG_BINS = 1024              # up to 0.01 e^20.48 ~ 8e6 s px
#: a sample agrees with its cluster's measurement when its tau is within this fraction of it
AGREEMENT = 0.2
#: a time after every FOE entry (µs)
_FOREVER = np.iinfo(np.int64).max
#: FOE entries the rotation history holds at most (41 s of ``foe_fit``'s 10 ms fits); entries
#: older than the longest baseline are dropped first
ANGLE_HISTORY = 4096


class TtcParams(NamedTuple):
    """Constants of :func:`process`; build with :func:`evchain.kernels.records.record`."""

    period_us: int              #: ticks at multiples of this, µs
    select_nearest: bool        #: obstacle: the cluster nearest the FOE (else the most active)
    select_min_activity: float  #: nearest: activity a cluster needs to be selected
    half_width: float           #: region B: largest |x - x_foe|, px
    min_below: float            #: region B: y - y_foe at least this, px
    min_dist: float             #: region B: distance from the FOE at least this, px
    min_speed: float            #: flow speed range, px/s
    max_speed: float
    min_tau: float              #: per-event tau range, s
    max_tau: float
    max_spread: float           #: credible clusters: relative spread of samples at most this
    init_size: float            #: half-size of a new cluster, px
    max_size: float             #: largest half-size, px
    join_margin: float          #: events this far outside a square still join it, px
    act_tau_us: float           #: decay of the activity, µs
    min_activity: float         #: clusters below this activity are removed
    max_age_us: float           #: samples older than this are not used, µs
    min_samples: int            #: samples a cluster estimate needs
    rel_floor: float            #: measurement noise floor (fraction of tau)
    q_s2_per_s: float           #: process noise of tau, s^2/s
    gate: float                 #: Kalman gate, sigma
    ground_test: bool           #: only clusters off the road plane can be the obstacle
    ground_tol: float           #: relative band around K that counts as road
    ground_memory_us: float     #: the ground votes' memory, µs
    ground_min_events: float    #: votes K needs before the ground test applies
    ground_fallback: bool       #: none off the road: select among all
    corridor: float             #: driving corridor half-width in camera heights (0: off)
    hold: bool                  #: keep the previous obstacle while it qualifies
    base_px: int                #: baseline tau over up to this many px (0: from the flow)
    base_age_us: float          #: longest baseline, µs
    base_width: int             #: baseline: pixels searched beside each step along the edge
    run_px: float               #: baseline: t_edge counts while its run is this many px of motion
    f: float                    #: focal length, px (0: the flow is not derotated)
    cx: float                   #: principal point, px
    cy: float


class TtcState(NamedTuple):
    """The state of :func:`process` (:func:`new_state`); updated in place."""

    clusters: np.ndarray     #: CLUSTER_STATE [max_clusters]
    samples_t: np.ndarray    #: float64 [max_clusters, ring]: sample times, µs
    samples_tau: np.ndarray  #: float64 [max_clusters, ring]: sample tau, s
    samples_kg: np.ndarray   #: float64 [max_clusters, ring]: sample tau * dy, s px
    samples_x: np.ndarray    #: float64 [max_clusters, ring]: sample position x, px
    samples_y: np.ndarray    #: float64 [max_clusters, ring]: sample position y, px
    carry: np.ndarray        #: CARRY [1]
    last_t: np.ndarray       #: float64 [2, H, W] (or [2, 0, 0]): last flow event's edge arrival, µs
    ground_hist: np.ndarray  #: float64 [KG_BINS]: the ground votes
    angle_t: np.ndarray      #: float64 [ANGLE_HISTORY]: times of the FOE entries kept, µs
    angle: np.ndarray        #: float64 [ANGLE_HISTORY, 3]: the rotation angle at each, rad


def new_state(max_clusters: int, ring: int, height: int, width: int,
              baseline: bool) -> TtcState:
    """Empty state: no cluster, no FOE, no votes, the first tick still to be set
    (:func:`start`); each pixel's last flow event's edge arrival only with ``baseline``."""
    carry = np.zeros(1, CARRY)
    carry["held_id"] = -1.0
    return TtcState(np.zeros(max_clusters, CLUSTER_STATE), np.zeros((max_clusters, ring)),
                    np.zeros((max_clusters, ring)), np.zeros((max_clusters, ring)),
                    np.zeros((max_clusters, ring)), np.zeros((max_clusters, ring)), carry,
                    np.full((2, height, width) if baseline else (2, 0, 0), -1e300),
                    np.zeros(KG_BINS), np.zeros(ANGLE_HISTORY), np.zeros((ANGLE_HISTORY, 3)))


def start(state: TtcState, first_tick_us: int) -> None:
    """Set the first tick (µs)."""
    state.carry["next_tick"] = float(first_tick_us)


def next_tick(state: TtcState) -> int:
    """The next tick, µs."""
    return int(state.carry["next_tick"][0])


def no_ttc_counts(state: TtcState) -> dict[str, int]:
    """The ticks without a TTC so far, by reason (:data:`NO_TTC_REASONS`)."""
    return {r: int(state.carry[r][0]) for r in NO_TTC_REASONS}


def slotless_events(state: TtcState) -> int:
    """The events so far that started no cluster because every slot held a live one."""
    return int(state.carry["no_slot"][0])


def ground_constant(state: TtcState) -> float:
    """The last estimate of the ground constant K, s px (0 before one)."""
    return float(state.carry["k_ground"][0])


@njit(cache=True)
def rotational_speed(px, py, nx, ny, wx, wy, wz, f, cx, cy):
    """The normal speed (px/s, along the unit normal (nx, ny)) of the flow that a camera
    turning at (wx, wy, wz) rad/s gives at (px, py): with ``X = (px - cx) / f``,
    ``Y = (py - cy) / f`` the rotational flow is ``u = f (X Y wx - (1 + X^2) wy + Y wz)``,
    ``v = f ((1 + Y^2) wx - X Y wy - X wz)`` (Longuet-Higgins and Prazdny 1980), whatever the
    depth."""
    X = (px - cx) / f
    Y = (py - cy) / f
    u = f * (X * Y * wx - (1.0 + X * X) * wy + Y * wz)
    v = f * ((1.0 + Y * Y) * wx - X * Y * wy - X * wz)
    return nx * u + ny * v


@njit(cache=True)
def event_tau(px, py, vx, vy, fx, fy, prm):
    """tau = (p - foe).v / |v|^2 for a flow event in region B, or -1 when it does not qualify.

    Region B: below the FOE by at least ``min_below`` px, ``|x - fx| <= half_width``, at least
    ``min_dist`` px from the FOE, diverging, speed in [min_speed, max_speed], tau in
    [min_tau, max_tau] (the fields of ``prm``).
    """
    rx = px - fx
    ry = py - fy
    if ry < prm.min_below or abs(rx) > prm.half_width:
        return -1.0
    if rx * rx + ry * ry < prm.min_dist * prm.min_dist:
        return -1.0
    s2 = vx * vx + vy * vy
    if not (s2 > 0.0) or s2 < prm.min_speed * prm.min_speed or s2 > prm.max_speed * prm.max_speed:
        return -1.0
    d = rx * vx + ry * vy
    if not (d > 0.0):
        return -1.0
    tau = d / s2
    if tau < prm.min_tau or tau > prm.max_tau:
        return -1.0
    return tau


@njit(cache=True)
def record_angle(angle_t, angle, g, t_us, wx, wy, wz, keep_us):
    """Append the FOE entry at ``t_us`` to the rotation history: the angle at the entry before
    plus its angular velocity (rad/s, that of the stretch up to ``t_us``) times the time since
    (0 at the first entry). When the history is full, the entries older than ``keep_us``
    before ``t_us`` are dropped but the newest of them (it brackets the oldest time still
    asked for), or the older half if none is."""
    n = int(g.n_angles)
    if n == angle_t.shape[0]:
        k = 0
        while k < n - 1 and angle_t[k + 1] <= t_us - keep_us:
            k += 1
        if k == 0:
            k = n // 2
        angle_t[:n - k] = angle_t[k:n].copy()
        angle[:n - k] = angle[k:n].copy()
        n -= k
    if n == 0:
        a0 = a1 = a2 = 0.0
    else:
        dt = (t_us - angle_t[n - 1]) * 1e-6
        a0 = angle[n - 1, 0] + wx * dt
        a1 = angle[n - 1, 1] + wy * dt
        a2 = angle[n - 1, 2] + wz * dt
    angle_t[n] = t_us
    angle[n, 0] = a0
    angle[n, 1] = a1
    angle[n, 2] = a2
    g.n_angles = n + 1


@njit(cache=True)
def angle_at(angle_t, angle, n, t_us, wx, wy, wz):
    """The rotation angle (rad, 3 axes) at ``t_us`` from the history's first ``n`` entries: the
    angular velocity of each entry holds over the stretch up to it, so linear between entries;
    after the newest entry its angular velocity (wx, wy, wz) goes on, before the oldest the
    oldest's angle holds; 0 without entries."""
    if n == 0:
        return 0.0, 0.0, 0.0
    if t_us >= angle_t[n - 1]:
        dt = (t_us - angle_t[n - 1]) * 1e-6
        return (angle[n - 1, 0] + wx * dt, angle[n - 1, 1] + wy * dt,
                angle[n - 1, 2] + wz * dt)
    if t_us <= angle_t[0]:
        return angle[0, 0], angle[0, 1], angle[0, 2]
    k = np.searchsorted(angle_t[:n], t_us)  # angle_t[k - 1] < t_us <= angle_t[k]
    s = (t_us - angle_t[k - 1]) / (angle_t[k] - angle_t[k - 1])
    return (angle[k - 1, 0] + s * (angle[k, 0] - angle[k - 1, 0]),
            angle[k - 1, 1] + s * (angle[k, 1] - angle[k - 1, 1]),
            angle[k - 1, 2] + s * (angle[k, 2] - angle[k - 1, 2]))


@njit(cache=True)
def baseline_tau(S, pol, px, py, nx, ny, d0, rot, ti, max_px, max_age_us, width, turns,
                 angle_t, angle, n_angles, wx, wy, wz, f, cx, cy):
    """tau from where the edge through (px, py) was earlier, or -1 when nothing qualifies.

    ``S[pol]`` holds the edge arrival time (µs) of each pixel's last flow event; ``ti`` is
    p's (the caller moves the tau forward to the event's time). Walking back from p against the
    unit normal n (the direction the edge moved in; ``d0 = (p - foe).n``) by 1..``max_px`` px,
    at each step the pixel nearest that point and those up to ``width`` px beside it along the
    edge (the tangent (-ny, nx)) are looked at, and the one that fired last, strictly before
    the previous step's time and within ``max_age_us`` of ``ti``, is taken: a far obstacle's
    edge crosses a pixel row in bursts that cover only part of the row, so the pixel straight
    behind p often did not fire when the edge crossed its row. For the farthest step q
    (``dd = (p - q).n`` px earlier, at time tq) an edge approaching at constant speed has the
    translational part of its position ``d(t) = D / (t_c - t)``. The camera's rotation between
    tq and ti moved the edge along n by ``shift``: with ``turns`` (a measured rotation) the
    rotational flow of p for the angle turned (:func:`angle_at` of the history, the newest
    entry's angular velocity wx, wy, wz after it; focal length f, principal point cx, cy),
    which over a baseline of several tenths of a second is not the latest angular velocity
    times the time (the pitch of a car's body swings at about 2 Hz); else ``rot dt``, ``rot``
    the latest rotational normal speed (px/s; with a rotation fitted to the flow, whose
    per-slab errors the angle would add up). So the translational part moved ``dd - shift`` in
    ``dt = ti - tq`` and ``tau = (d0 - dd + shift) dt / (dd - shift)``, which must be
    positive with the edge on the same side of the FOE at tq (``(d0 - dd + shift) d0 > 0``):
    positions and times only, over a baseline as long as the edge took, no flow magnitude.
    Without rotation ``tau = (d0 - dd) dt / dd``.
    """
    h = S.shape[1]
    w = S.shape[2]
    ix = int(math.floor(px + 0.5))
    iy = int(math.floor(py + 0.5))
    ai0 = ai1 = ai2 = 0.0
    if turns:
        ai0, ai1, ai2 = angle_at(angle_t, angle, n_angles, ti, wx, wy, wz)
    tprev = ti
    tau = -1.0
    for k in range(1, max_px + 1):
        bx = px - k * nx
        by = py - k * ny
        if int(math.floor(bx + 0.5)) == ix and int(math.floor(by + 0.5)) == iy:
            continue  # still in p's own pixel
        tq = -math.inf
        qx = -1
        qy = -1
        for j in range(-width, width + 1):
            cx_ = int(math.floor(bx - j * ny + 0.5))
            cy_ = int(math.floor(by + j * nx + 0.5))
            if cx_ < 0 or cy_ < 0 or cx_ >= w or cy_ >= h or (cx_ == ix and cy_ == iy):
                continue
            tc = S[pol, cy_, cx_]
            if tc < tprev and ti - tc <= max_age_us and tc > tq:
                tq = tc
                qx = cx_
                qy = cy_
        if qx < 0:
            break
        dd = (px - qx) * nx + (py - qy) * ny
        if turns:
            aq0, aq1, aq2 = angle_at(angle_t, angle, n_angles, tq, wx, wy, wz)
            shift = rotational_speed(px, py, nx, ny, ai0 - aq0, ai1 - aq1, ai2 - aq2, f, cx,
                                     cy)
        else:
            shift = rot * ((ti - tq) * 1e-6)
        dk = d0 - dd + shift
        dt = dd - shift
        if not (dd > 0.0) or not (dk * d0 > 0.0) or not (dt * d0 > 0.0):
            break
        tau = dk * (ti - tq) * 1e-6 / dt
        tprev = tq
    return tau


@njit(cache=True)
def ground_vote(H, carry, kg, t_us, memory_us):
    """Add kg = tau * dy > 0 of an event at ``t_us`` to the ground histogram ``H`` (bins of
    ln kg), weighted ``exp((t_us - votes_t_ref) / memory_us)`` (older votes fade with that
    memory); ``carry[0]`` counts the votes in ``n_votes`` and keeps the weights' reference time
    ``votes_t_ref`` (the first vote's, moved on with a rescale before the weights overflow)."""
    if not (kg > 0.0):
        return
    b = int(math.floor((math.log(kg) - KG_LN_MIN) / KG_BIN))
    if b < 0 or b >= H.shape[0]:
        return
    if carry[0].n_votes == 0.0:
        carry[0].votes_t_ref = t_us
    w = math.exp((t_us - carry[0].votes_t_ref) / memory_us)
    if w > 1e100:
        for j in range(H.shape[0]):
            H[j] /= w
        carry[0].votes_t_ref = t_us
        w = 1.0
    H[b] += w
    carry[0].n_votes += 1.0


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


# -- per tick: the clusters' estimates and the obstacle -----------------------------------------


@njit(cache=True)
def _select(a, n, k):
    """Reorder ``a[:n]`` (no NaN) so that ``a[k]`` holds the value a sort would put
    there, with none larger before it and none smaller after it (Hoare's selection); returns
    ``a[k]``."""
    lo = 0
    hi = n - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i = lo
        j = hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@njit(cache=True)
def median(a, n):
    """The median of ``a[:n]`` (n >= 1, no NaN): the middle value, or the mean of the
    two middle values; reorders ``a[:n]``."""
    m = _select(a, n, n // 2)
    if n % 2 == 1:
        return m
    lower = a[0]  # the largest of the n // 2 smallest
    for j in range(1, n // 2):
        lower = max(lower, a[j])
    return 0.5 * (lower + m)


@njit(cache=True)
def _median_mad(buf, n):
    """Median and median absolute deviation of ``buf[:n]`` (overwritten)."""
    med = median(buf, n)
    for j in range(n):
        buf[j] = abs(buf[j] - med)
    return med, median(buf, n)


@njit(cache=True)
def _recent_kg(ST, SK, k, nb, T, max_age_us, buf):
    """tau * dy of cluster k's samples at most ``max_age_us`` old at T into ``buf``; their
    number."""
    n = 0
    for j in range(nb):
        age = T - ST[k, j]
        if age <= max_age_us:
            buf[n] = SK[k, j]
            n += 1
    return n


@njit(cache=True)
def _recent_tau(ST, SV, k, nb, T, max_age_us, buf):
    """Cluster k's samples at most ``max_age_us`` old at T, each moved forward to T at
    -1 s/s, into ``buf``; their number."""
    n = 0
    for j in range(nb):
        age = T - ST[k, j]
        if age <= max_age_us:
            buf[n] = SV[k, j] - age * 1e-6
            n += 1
    return n


@njit(cache=True)
def _newest(ST, c, k):
    """The time of cluster ``c``'s (slot k's) newest sample (µs): the last one added (events
    come in time order; the cluster has at least one sample)."""
    return ST[k, (c.ring_pos - 1) % ST.shape[1]]


@njit(cache=True)
def _fuse(c, med, r, T, gate):
    """Fuse the measurement ``med`` (variance ``r``) into the cluster's predicted tau: the first
    one starts it; a gated-out one counts a miss (three in a row restart from the
    measurement); else a 1-D Kalman update."""
    if not c.has_tau > 0.0:
        c.tau = med
        c.var = r
        c.has_tau = 1.0
        c.t_tau = T
        c.misses = 0.0
        return
    innov = med - c.tau
    s = c.var + r
    if innov * innov > gate * gate * s:
        c.misses += 1.0
        if c.misses >= 3.0:  # the measurements insist: restart from them
            c.tau = med
            c.var = r
            c.misses = 0.0
        return
    c.misses = 0.0
    gain = c.var / s
    c.tau += gain * innov
    c.var = (1.0 - gain) * c.var


@njit(cache=True)
def _agreeing_samples(c, k, ST, SV, SK, SX, SY, T, k_ground, med, buf, prm):
    """Cluster k's samples at most ``max_age_us`` old at T whose tau (moved forward to T) lies
    within ``AGREEMENT`` of the measurement ``med``: the cluster is reported at their median
    position (left as it is when none agrees), and with at least ``min_samples`` of them its
    ground ratio rho is their median tau * dy over K. Returns their number. ``buf`` holds
    three rings."""
    ring = ST.shape[1]
    m = 0
    for j in range(c.n_samples):
        age = T - ST[k, j]
        if age <= prm.max_age_us and abs(SV[k, j] - age * 1e-6 - med) <= AGREEMENT * med:
            buf[m] = SX[k, j]
            buf[ring + m] = SY[k, j]
            buf[2 * ring + m] = SK[k, j]
            m += 1
    if m > 0:
        c.mx = median(buf, m)
        c.my = median(buf[ring:], m)
    if m >= prm.min_samples and k_ground > 0.0:
        c.rho = median(buf[2 * ring:], m) / k_ground
    return m


@njit(cache=True)
def _cluster_estimate(cl, k, ST, SV, SK, SX, SY, T, k_ground, buf, prm):
    """Update cluster k's fused tau at tick time T from its recent samples (median, MAD), its
    ground ratio rho (median of tau * dy over K, of the samples agreeing with the measurement
    where enough do; left as it is while K is unknown) and where its agreeing samples lie."""
    c = cl[k]
    nb = c.n_samples
    n = _recent_tau(ST, SV, k, nb, T, prm.max_age_us, buf)
    if c.has_tau > 0.0:  # predict: tau falls 1 s per s
        dt = (T - c.t_tau) * 1e-6
        c.tau -= dt
        c.var += prm.q_s2_per_s * dt
        c.t_tau = T
    if n < prm.min_samples:
        return
    med, mad = _median_mad(buf, n)
    m = _agreeing_samples(c, k, ST, SV, SK, SX, SY, T, k_ground, med, buf, prm)
    if m < prm.min_samples and k_ground > 0.0:  # too few agree: all its recent samples
        c.rho = median(buf, _recent_kg(ST, SK, k, nb, T, prm.max_age_us, buf)) / k_ground
    c.t_meas = _newest(ST, c, k)
    c.spread = 1.4826 * mad / med if med > 0.0 else math.inf
    sigma = 1.4826 * mad / math.sqrt(n) + prm.rel_floor * abs(med)
    _fuse(c, med, sigma * sigma + 1e-12, T, prm.gate)


@njit(cache=True)
def _candidate(c, a, g, prm, use_ground):
    """Whether a reported cluster (activity ``a``) can be the obstacle: (considered, d, off_road).
    Considered: active enough (nearest selection) and reaching into the driving corridor (the
    lateral gap between its square and the FOE at most ``corridor`` times the depth of its
    lower edge below the FOE). d: the distance of its square's nearest point from the FOE
    (nearest selection; else 0). off_road: not ruled out by the ground test (rho < 1 -
    ground_tol, or the test not in use)."""
    if prm.select_nearest and a < prm.select_min_activity:
        return False, 0.0, False
    if prm.corridor > 0.0:
        gap = max(0.0, abs(c.cx - g.foe_x) - c.size)
        if gap > prm.corridor * (c.cy + c.size - g.foe_y):
            return False, 0.0, False  # beside the driving corridor
    d = 0.0
    if prm.select_nearest:
        ddx = max(0.0, abs(c.cx - g.foe_x) - c.size)
        ddy = max(0.0, abs(c.cy - g.foe_y) - c.size)
        d = math.sqrt(ddx * ddx + ddy * ddy)
    return True, d, not (use_ground and not (c.rho < 1.0 - prm.ground_tol))


@njit(cache=True)
def _credible(c, g, T, prm):
    """Whether a cluster's tau can be reported at tick T: its samples agree (relative spread
    at most ``max_spread``: one approaching surface has one TTC, a cluster of rotational flow
    or of several objects does not), the newest sample of its last measurement is no older
    than its tau (a tau predicted forward over more than the time left to contact rests on
    no data: a cluster kept alive without new samples counted down to 0 that way) and its
    tau lies within the
    per-event bounds (at least ``min_tau``, and its centre's distance from the FOE over tau,
    the image speed it implies, at most ``max_speed``); fusion and the forward prediction can
    leave both bounds."""
    if not (c.spread <= prm.max_spread) or c.tau < prm.min_tau:
        return False
    if T - c.t_meas > c.tau * 1e6:
        return False
    dx = c.cx - g.foe_x
    dy = c.cy - g.foe_y
    return dx * dx + dy * dy <= (c.tau * prm.max_speed) ** 2


@njit(cache=True, inline="always")
def _better(d, a, best_d, best_a):
    """Nearer, or as near and more active."""
    return d < best_d or (d == best_d and a > best_a)


@njit(cache=True, inline="always")
def _position(c):
    """Where cluster ``c`` is reported: where its samples agreeing with its last measurement
    lie, else (none yet) its square's centre."""
    if c.mx == c.mx:
        return c.mx, c.my
    return c.cx, c.cy


@njit(cache=True)
def _emit_cluster(out, n, T, c, a, k_ground):
    """Row n of the ``ttc_clusters`` output: the cluster at tick T with activity ``a``."""
    out[n].t = T
    out[n].cluster = c.id
    out[n].x, out[n].y = _position(c)
    out[n].size_px = c.size
    out[n].tau_s = c.tau
    out[n].support = a
    rho = c.rho
    out[n].ground_ratio = rho if (k_ground > 0.0 and rho == rho) else -1.0


@njit(cache=True)
def _emit_obstacle(out, n, T, c, support):
    """Row n of the ``ttc`` output: the obstacle's cluster at tick T."""
    out[n].t = T
    out[n].tau_s = c.tau
    out[n].cluster = c.id
    out[n].x, out[n].y = _position(c)
    out[n].support = support


@njit(cache=True)
def _tick(state, prm, half_bins, buf, ttc_out, no, clusters_out, nc):
    """The tick at ``next_tick``: the ground constant, every live cluster's decay, estimate and
    row, the obstacle's row; moves ``next_tick`` on by a period. Returns the rows written
    (no, nc)."""
    cl, ST, SV, SK, SX, SY, carry, _, hist, _, _ = state
    g = carry[0]
    T = g.next_tick
    if g.n_votes >= prm.ground_min_events:
        g.k_ground = ground_mode(hist, half_bins)
    k_ground = g.k_ground if g.n_votes >= prm.ground_min_events else 0.0
    use_ground = prm.ground_test and k_ground > 0.0
    best = -1
    best_sup = 0.0
    best_d = 1e300
    held = -1
    fb = -1  # the fallback choice (ground test ignored)
    fb_sup = 0.0
    fb_d = 1e300
    n_considered = 0
    n_credible = 0
    for k in range(cl.shape[0]):
        c = cl[k]
        if c.active == 0:
            continue
        a = c.activity * math.exp(-(T - c.t_last) / prm.act_tau_us)
        if a < prm.min_activity:
            c.active = 0
            continue
        _cluster_estimate(cl, k, ST, SV, SK, SX, SY, T, k_ground, buf, prm)
        if c.has_tau > 0.0 and c.tau <= 0.0:  # passed or hit: drop it
            c.active = 0
            continue
        if not (c.has_tau > 0.0 and nc < clusters_out.shape[0]):
            continue
        _emit_cluster(clusters_out, nc, T, c, a, k_ground)
        nc += 1
        considered, d, off_road = _candidate(c, a, g, prm, use_ground)
        if not considered:
            continue
        n_considered += 1
        if not _credible(c, g, T, prm):
            continue
        n_credible += 1
        if _better(d, a, fb_d, fb_sup):
            fb_d = d
            fb_sup = a
            fb = k
        if not off_road:
            continue  # lies on the road (or its rho is not known yet)
        if prm.hold and c.id == g.held_id:
            held = k
        if _better(d, a, best_d, best_sup):
            best_d = d
            best_sup = a
            best = k
    if held >= 0:
        best = held
        best_sup = cl[held].activity * math.exp(-(T - cl[held].t_last) / prm.act_tau_us)
    if best < 0 and (prm.ground_fallback or not use_ground):
        best = fb
        best_sup = fb_sup
    g.held_id = cl[best].id if best >= 0 else -1.0
    if best >= 0 and no < ttc_out.shape[0]:
        _emit_obstacle(ttc_out, no, T, cl[best], best_sup)
        no += 1
    elif best < 0:
        if g.has_foe == 0.0:
            g.no_foe += 1.0
        elif n_considered == 0:
            g.no_cluster += 1.0
        elif n_credible == 0:
            g.not_credible += 1.0
        else:
            g.on_road += 1.0
    g.next_tick = T + prm.period_us
    return no, nc


# -- per event: tau and the clusters ----------------------------------------------------------


@njit(cache=True)
def _apply_foe(foe, j, t_us, g, angle_t, angle, keep_us):
    """Take the FOE entries from j on with time <= ``t_us`` (NaN entries are skipped), with
    their angular velocities, each added to the rotation history (:func:`record_angle`);
    returns the index of the first one left."""
    foe_t, foe_x, foe_y, foe_wx, foe_wy, foe_wz, measured = foe
    while j < foe_t.shape[0] and foe_t[j] <= t_us:
        if foe_x[j] == foe_x[j] and foe_y[j] == foe_y[j]:
            g.has_foe = 1.0
            g.foe_x = foe_x[j]
            g.foe_y = foe_y[j]
            g.foe_wx = foe_wx[j]
            g.foe_wy = foe_wy[j]
            g.foe_wz = foe_wz[j]
            g.measured = measured[j]
            record_angle(angle_t, angle, g, float(foe_t[j]), foe_wx[j], foe_wy[j], foe_wz[j],
                         keep_us)
        j += 1
    return j


@njit(cache=True)
def _nearest_cluster(cl, px, py, prm):
    """The nearest cluster (inf-norm) whose square, widened by the join margin, holds p:
    (k, distance), k -1 for none (most events join one: no activity is decayed for them)."""
    kb = -1
    db = 1e300
    for k in range(cl.shape[0]):
        c = cl[k]
        if c.active == 0:
            continue
        d = max(abs(px - c.cx), abs(py - c.cy))
        if d <= c.size + prm.join_margin and d < db:
            db = d
            kb = k
    return kb, db


@njit(cache=True)
def _free_slot(cl, ti, prm):
    """The slot a new cluster takes at ti: the first inactive one, or the first decayed below
    ``min_activity``; -1 when every slot holds a live cluster (a new cluster never displaces
    one: a one-event cluster in place of one with samples, on a crowded sensor often the young
    cluster of a far obstacle). Only asked when no cluster holds the event."""
    free = -1
    for k in range(cl.shape[0]):
        c = cl[k]
        if c.active == 0:
            if free < 0:
                free = k
            continue
        a = c.activity * math.exp(-(ti - c.t_last) / prm.act_tau_us)
        if a < prm.min_activity and free < 0:
            free = k
    return free


@njit(cache=True)
def _new_cluster(c, g, px, py, ti, prm):
    """Start cluster ``c`` at p with the next id."""
    c.id = int(g.next_id)
    g.next_id += 1.0
    c.active = 1
    c.n_samples = 0
    c.ring_pos = 0
    c.cx = px
    c.cy = py
    c.size = prm.init_size
    c.activity = 1.0
    c.t_last = ti
    c.has_tau = 0.0
    c.misses = 0.0
    c.tau = 0.0
    c.var = 0.0
    c.t_tau = ti
    c.rho = math.nan
    c.spread = math.inf
    c.t_meas = ti
    c.mx = math.nan
    c.my = math.nan


@njit(cache=True)
def _join(c, px, py, ti, dist, prm):
    """An event at distance ``dist`` (inf-norm) joins cluster ``c``: its activity decays to ti
    and counts the event; its square grows towards events near or beyond the boundary, then
    its centre moves towards p by 1 / activity."""
    a = c.activity * math.exp(-(ti - c.t_last) / prm.act_tau_us) + 1.0
    c.activity = a
    c.t_last = ti
    if dist > c.size:
        c.size = min(prm.max_size, dist)
    c.cx += (px - c.cx) / a
    c.cy += (py - c.cy) / a


@njit(cache=True)
def _add_sample(c, ST, SV, SK, SX, SY, k, ti, tau, kg, px, py):
    """Append (ti, tau, kg) at (px, py) to the ring of samples of cluster ``c`` (slot k)."""
    p = c.ring_pos
    ring = ST.shape[1]
    ST[k, p] = ti
    SV[k, p] = tau
    SK[k, p] = kg
    SX[k, p] = px
    SY[k, p] = py
    c.ring_pos = (p + 1) % ring
    if c.n_samples < ring:
        c.n_samples += 1


@njit(cache=True, nogil=True)
def process(events, foe, state, prm, t_end, ttc_out, clusters_out):
    """Process one packet; returns (rows of ``ttc_out``, rows of ``clusters_out``) written.

    Ticks at multiples of ``period_us`` see the events before them (cut-independent). FOE
    entries apply to the events at or after their time. Only credible clusters
    (:func:`_credible`) can be the obstacle; a tick without one has no obstacle row, and the
    carry counts why (:data:`NO_TTC_REASONS`). With ``ground_test`` only clusters
    with rho < 1 - ground_tol (nearer than the road at their rows) can be the obstacle once K
    has seen ``ground_min_events`` events; when there is none, ``ground_fallback`` selects
    among all clusters, else the tick has no obstacle row. With ``corridor`` > 0 a cluster must
    reach into the driving corridor: the lateral gap between its square and the FOE at most
    ``corridor`` times the depth of its lower edge below the FOE (a road point at (dx, dy)
    below the FOE lies dx / dy camera heights to the side). With ``hold`` the previous tick's
    obstacle stays selected while it qualifies.

    Parameters
    ----------
    events : tuple (x, y, t, p, vx, vy, t_edge)
        The flow events in time order: x, y uint16 [n] px; t int64 [n] µs; p int8 [n]
        polarity; vx, vy float32 [n] flow, px/s; t_edge int64 [n] µs, when the event's edge
        reached its pixel (the baseline compares these).
    foe : tuple (t, x, y, wx, wy, wz, measured)
        FOE entries: t int64 [m] µs, x, y float64 [m] px (NaN: no estimate), the camera's
        angular velocity wx, wy, wz float64 [m] rad/s (0 where not estimated), measured
        float64 [m]: 1 where it is measured (the gyro's), 0 where fitted to the flow.
    state : TtcState
        Updated in place (:func:`new_state`, :func:`start`).
    prm : TtcParams
        The constants.
    t_end : int
        End of the packet's time slice, µs: ticks before it are made.
    ttc_out : structured ndarray [>= ticks] (t, tau_s, cluster, x, y, support)
        Out: the obstacle per tick (t µs, tau s, cluster id, centre px, activity).
    clusters_out : structured ndarray [>= ticks x clusters]
        (t, cluster, x, y, size_px, tau_s, support, ground_ratio). Out: every live cluster
        with a tau per tick (ground_ratio -1 while K is unknown).

    Returns
    -------
    (int, int)
        The rows written into ``ttc_out`` and ``clusters_out``.
    """
    x, y, t, pol, vx, vy, te = events
    foe_t = foe[0]
    # the state's arrays as locals, passed on one by one (a tuple of arrays passed on costs
    # reference counts per event)
    cl, ST, SV, SK, SX, SY, carry, last_t, hist, angle_t, angle = state
    g = carry[0]
    half_bins = int(round(math.log(1.0 + prm.ground_tol) / KG_BIN))
    buf = np.empty(3 * ST.shape[1], np.float64)  # a ring's values, or three (agreeing)
    n = t.shape[0]
    j = 0
    i = 0
    no = 0
    nc = 0
    while True:
        t_next = t[i] if i < n else t_end
        while g.next_tick < t_next or (i < n and g.next_tick == t_next):
            no, nc = _tick(state, prm, half_bins, buf, ttc_out, no, clusters_out, nc)
        if i >= n:
            break
        ti = t[i]
        if j < foe_t.shape[0] and foe_t[j] <= ti:  # (a call per event costs the arrays'
            # reference counts: the entries come once per 10 ms)
            j = _apply_foe(foe, j, ti, g, angle_t, angle, prm.base_age_us)
        px = float(x[i])
        py = float(y[i])
        evx = np.float64(vx[i])
        evy = np.float64(vy[i])
        sp = math.sqrt(evx * evx + evy * evy)
        rot = 0.0
        if prm.f > 0.0 and sp > 0.0 and (g.foe_wx != 0.0 or g.foe_wy != 0.0
                                         or g.foe_wz != 0.0):
            # the flow's rotational part along its normal
            rot = rotational_speed(px, py, evx / sp, evy / sp, g.foe_wx, g.foe_wy, g.foe_wz,
                                   prm.f, prm.cx, prm.cy)
        # when the event's edge reached its pixel: the start of the pixel's run of events,
        # unless the run lasted longer than the edge takes to cross run_px px (several edges)
        ta = float(te[i])
        if (ti - ta) * 1e-6 * sp > prm.run_px:
            ta = float(ti)
        tau = -1.0
        if g.has_foe > 0.0:  # from the translational part of the normal flow, sp - rot
            if rot != 0.0:
                tau = event_tau(px, py, evx - rot * evx / sp, evy - rot * evy / sp, g.foe_x,
                                g.foe_y, prm)
            else:
                tau = event_tau(px, py, evx, evy, g.foe_x, g.foe_y, prm)
        if tau > 0.0 and prm.base_px > 0:  # from where the edge was earlier
            d0 = tau * (sp - rot)  # (p - foe).n
            tau = baseline_tau(last_t, 1 if pol[i] > 0 else 0, px, py, evx / sp, evy / sp,
                               d0, rot, ta, prm.base_px, prm.base_age_us, prm.base_width,
                               prm.f > 0.0 and g.measured > 0.0, angle_t, angle,
                               int(g.n_angles), g.foe_wx, g.foe_wy, g.foe_wz, prm.f, prm.cx,
                               prm.cy)
            if tau > 0.0:
                tau -= (ti - ta) * 1e-6  # moved forward from the arrival to the event
            if tau < prm.min_tau or tau > prm.max_tau:
                tau = -1.0
        if tau > 0.0:  # to its cluster: the nearest whose widened square holds it, or a new one
            kg = tau * (py - g.foe_y)
            kb, db = _nearest_cluster(cl, px, py, prm)
            if kb >= 0:
                _join(cl[kb], px, py, ti, db, prm)
            else:
                kb = _free_slot(cl, ti, prm)
                if kb >= 0:
                    _new_cluster(cl[kb], g, px, py, ti, prm)
                else:
                    g.no_slot += 1.0
            if kb >= 0:
                _add_sample(cl[kb], ST, SV, SK, SX, SY, kb, ti, tau, kg, px, py)
                # K learns from events of clusters not (yet) known to be off the road
                if not (cl[kb].rho < 1.0 - prm.ground_tol):
                    ground_vote(hist, carry, kg, float(ti), prm.ground_memory_us)
        _remember_time(last_t, x[i], y[i], pol[i], ta)
        i += 1
    _apply_foe(foe, j, _FOREVER, g, angle_t, angle, prm.base_age_us)  # they count next
    return no, nc


@njit(cache=True)
def _remember_time(last_t, x, y, pol, ti):
    """The edge arrival time of the pixel's last flow event (kept only for the baseline
    tau)."""
    if last_t.shape[1] > 0:
        qx = int(x)
        qy = int(y)
        if 0 <= qx < last_t.shape[2] and 0 <= qy < last_t.shape[1]:
            last_t[1 if pol > 0 else 0, qy, qx] = ti
