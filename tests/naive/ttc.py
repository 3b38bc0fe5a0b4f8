"""Plain Python references of the ``ttc`` kernel: region B and tau per event, the ground
constant, the baseline tau, and the whole filter (clusters, fusion, selection)."""

from __future__ import annotations

import math
from collections import deque

import numpy as np

#: the px values the ttc tests were written with (the reference camera's, and 8 px from the
#: FOE), given to ``Ttc.Params``: left null they would follow the tests' small sensors' focal
#: lengths
PX = dict(region_b_half_width_px=60.0, min_distance_px=8.0, min_speed_pxs=2.0,
          max_speed_pxs=20_000.0, cluster_size_px=6.0, max_cluster_size_px=15.0,
          join_margin_px=4.0)


def event_tau_naive(px, py, vx, vy, fx, fy, half_width, min_below, min_dist, min_speed,
                    max_speed, min_tau, max_tau) -> np.ndarray:
    """Vectorised: tau = (p - foe).v / |v|^2 where the event qualifies, else -1."""
    px, py, vx, vy = (np.asarray(a, np.float64) for a in (px, py, vx, vy))
    rx, ry = px - fx, py - fy
    speed = np.hypot(vx, vy)
    d = rx * vx + ry * vy
    ok = ((ry >= min_below) & (np.abs(rx) <= half_width) & (np.hypot(rx, ry) >= min_dist)
          & (speed > 0) & (speed >= min_speed) & (speed <= max_speed) & (d > 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(ok, d / np.where(speed > 0, speed * speed, 1.0), -1.0)
    ok &= (tau >= min_tau) & (tau <= max_tau)
    return np.where(ok, tau, -1.0)


def ground_constant_naive(kg, t_us, tol, memory_us, k_min=0.01, width=0.02,
                          bins=1024) -> tuple[float, int]:
    """The ground constant K after the votes ``kg`` (tau * dy) at times ``t_us``, and the number
    of votes: every positive kg whose bin floor((ln kg - ln k_min) / width) lies in [0, bins)
    votes with weight exp(t / memory) (only the ratios matter); K is the weighted mean bin
    centre (in ln) of the window of 2 round(ln(1 + tol) / width) + 1 bins with the most weight
    (the first of equals), 0 without votes."""
    ln_min = math.log(k_min)
    kg = np.asarray(kg, np.float64)
    t = np.asarray(t_us, np.float64)
    ok = kg > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        b = np.floor((np.log(np.where(ok, kg, 1.0)) - ln_min) / width)
    ok &= (b >= 0) & (b < bins)
    if not ok.any():
        return 0.0, 0
    w = np.exp((t[ok] - t[ok].max()) / memory_us)
    h = np.bincount(b[ok].astype(np.int64), w, minlength=bins)
    win = 2 * int(round(math.log(1.0 + tol) / width)) + 1
    sums = [h[j:j + win].sum() for j in range(max(1, bins - win + 1))]
    j = int(np.argmax(sums))
    c = np.arange(j, min(j + win, bins)) + 0.5
    k = math.exp(ln_min + width * float((h[j:j + win] * c).sum() / h[j:j + win].sum()))
    return k, int(ok.sum())


def rotational_speed_naive(px, py, nx, ny, w, f, cx, cy) -> float:
    """n . B(p) w: the normal speed of a pinhole camera's rotational flow at p (px/s) for the
    angular velocity w (rad/s), from the flow vector itself."""
    X, Y = (px - cx) / f, (py - cy) / f
    B = f * np.array([[X * Y, -(1 + X * X), Y], [1 + Y * Y, -X * Y, -X]])
    return float(np.array([nx, ny]) @ (B @ np.asarray(w, np.float64)))


def angle_naive(history, t, w_last) -> np.ndarray:
    """The camera's rotation angle (rad) at t from the FOE entries so far, ``history`` a list
    of (time µs, angle): piecewise linear between entries (each entry's angular velocity holds
    over the stretch up to it), after the newest going on at ``w_last`` (its angular velocity),
    before the oldest the oldest's angle; 0 without entries."""
    if not history:
        return np.zeros(3)
    times = [h[0] for h in history]
    if t >= times[-1]:
        return history[-1][1] + np.asarray(w_last) * ((t - times[-1]) * 1e-6)
    if t <= times[0]:
        return history[0][1]
    k = next(i for i, tk in enumerate(times) if tk >= t)
    (t0, a0), (t1, a1) = history[k - 1], history[k]
    return a0 + (t - t0) / (t1 - t0) * (a1 - a0)


def baseline_tau_naive(last_t, px, py, nx, ny, d0, ti, max_px, max_age_us, width=0,
                       shift_of=None) -> float:
    """tau from the pixel the edge through p crossed earliest within the walk: step back
    k = 1..max_px px against the unit normal n (skip a step whose nearest pixel is p's own);
    at each step take, among the nearest pixels of the points j px beside it along the
    tangent (-ny, nx), |j| <= ``width``, inside the image and not p's own, those strictly
    older than the previous step's time and at most ``max_age_us`` old, the newest; stop at a
    step without one, or where the translational part of the edge's position (its position
    less the rotation's displacement along n since tq, ``shift_of(tq)`` px, 0 without it) is
    not between the FOE and p; tau = d_tq dt / (d0 - d_tq) with d_tq = d0 - dd + shift the
    translational distance from the FOE at tq, for the last pixel taken (dd its distance
    behind p along n), -1 when there is none."""
    h, w = last_t.shape
    own = (int(np.floor(px + 0.5)), int(np.floor(py + 0.5)))
    tprev, tau = ti, -1.0
    for k in range(1, max_px + 1):
        bx, by = px - k * nx, py - k * ny
        if (int(np.floor(bx + 0.5)), int(np.floor(by + 0.5))) == own:
            continue
        found = []
        for j in range(-width, width + 1):
            q = (int(np.floor(bx - j * ny + 0.5)), int(np.floor(by + j * nx + 0.5)))
            if not (0 <= q[0] < w and 0 <= q[1] < h) or q == own:
                continue
            tq = last_t[q[1], q[0]]
            if tq < tprev and ti - tq <= max_age_us:
                found.append((tq, -j, q))
        if not found:
            break
        # the newest; of equal times the first in j (the kernel keeps the first maximum)
        tq, _, q = max(found, key=lambda c: (c[0], c[1]))
        dd = (px - q[0]) * nx + (py - q[1]) * ny
        dt = (ti - tq) * 1e-6
        d_tq = d0 - dd + (shift_of(tq) if shift_of else 0.0)
        if not (dd > 0 and d_tq * d0 > 0 and (d0 - d_tq) * d0 > 0):
            break
        tau, tprev = d_tq * dt / (d0 - d_tq), tq
    return tau


# -- the whole filter: clusters, fusion, selection ------------------------------------------------


def median(values) -> float:
    """Median of a non-empty list: the middle value, or the mean of the two middle values."""
    v = sorted(values)
    n = len(v)
    return v[n // 2] if n % 2 == 1 else 0.5 * (v[n // 2 - 1] + v[n // 2])


#: a sample agrees with its cluster's measurement when its tau is within this fraction of it
AGREEMENT = 0.2


class Cluster:
    """One square cluster with its recent samples (time µs, tau s, tau * dy s px, x px,
    y px)."""

    def __init__(self, ident, x, y, t, size, ring):
        self.id = ident
        self.cx, self.cy, self.size = x, y, size
        self.activity, self.t_last = 1.0, float(t)
        self.samples = deque(maxlen=ring)
        self.tau = None          # fused tau (s), None before the first estimate
        self.var = 0.0
        self.t_tau = float(t)
        self.misses = 0
        self.rho = math.nan      # median(tau * dy) / K
        self.spread = math.inf   # 1.4826 MAD / median of the samples at the last measurement
        self.t_meas = float(t)   # the newest sample's time at the last measurement (µs)
        self.mx = self.my = None  # median position of the samples agreeing with it

    def position(self):
        """Where it is reported: its agreeing samples' median position, else its centre."""
        return (self.cx, self.cy) if self.mx is None else (self.mx, self.my)

    def activity_at(self, t, tau_us):
        return self.activity * math.exp(-(t - self.t_last) / tau_us)


def ttc_naive(packets, q, width, height, no_ttc=None, f=None, cx=None, cy=None):
    """The ``ttc`` filter in plain Python, packet by packet (FOE entries count from the first
    event at or after their time, and from the end of the packet that carries them; a tick at T
    sees the events before T). ``q``: a ``Ttc.Params``. Returns (ttc rows, cluster rows) as
    lists of tuples in the order of the series' fields; ``no_ttc`` (a dict, filled if given)
    counts the ticks without a row by reason, and under ``no_slot`` the events that started no
    cluster because every slot held a live one (a new cluster takes an empty slot or one
    whose cluster has decayed below ``min_activity``, never a live cluster's). Where the FOE
    entries carry the camera's angular velocity (``rotation`` 1) and the geometry a focal
    length ``f`` (principal point ``cx``, ``cy``), each event's tau is that of its flow less
    the rotational flow's normal component. ``q`` holds the values on the camera
    (``Ttc.params_on``: no null px)."""
    slots = [None] * q.max_clusters        # None or a Cluster (inactive slots are None)
    next_id = 0
    foe = None
    omega = np.zeros(3)  # the latest entry's angular velocity, rad/s
    measured = False     # whether it is measured (the gyro's), not fitted to the flow
    angles = []          # (time, rotation angle) at every FOE entry
    votes_kg, votes_t = [], []
    k_ground = 0.0
    held = -1
    last_t = np.full((2, height, width), -1e300)
    period = q.estimate_every_us
    tick = None
    ttc_rows, cluster_rows = [], []
    reasons = {"no_foe": 0, "no_cluster": 0, "not_credible": 0, "on_road": 0, "no_slot": 0}
    max_spread = math.inf if q.max_rel_spread is None else q.max_rel_spread

    def apply_foe(entries, upto):
        nonlocal foe, omega, measured
        while entries and entries[0][0] <= upto:
            ft, fx, fy, w, meas = entries.pop(0)
            if fx == fx and fy == fy:
                foe, omega, measured = (fx, fy), w, meas
                angles.append((ft, angle_naive(angles, ft, w)))

    def do_tick(T):
        nonlocal k_ground, held
        k_now = 0.0
        n_votes = sum(1 for kg in votes_kg if kg > 0 and 0 <= _bin(kg) < 1024)
        if n_votes >= q.ground_min_events:
            k_ground = ground_constant_naive(votes_kg, votes_t, q.ground_tolerance,
                                             q.ground_memory_ms * 1000.0)[0]
            k_now = k_ground
        use_ground = q.ground_test and k_now > 0.0
        best = fb = held_k = None
        considered = credible = 0
        for k, c in enumerate(slots):
            if c is None:
                continue
            a = c.activity_at(T, q.activity_tau_ms * 1000.0)
            if a < q.min_activity:
                slots[k] = None
                continue
            estimate(c, T, k_now)
            if c.tau is not None and c.tau <= 0.0:
                slots[k] = None
                continue
            if c.tau is None:
                continue
            rho = c.rho if (k_now > 0.0 and c.rho == c.rho) else -1.0
            cluster_rows.append((T, c.id, *c.position(), c.size, c.tau, a, rho))
            if q.select == "nearest_foe" and a < q.select_min_activity:
                continue
            gx = max(0.0, abs(c.cx - foe[0]) - c.size)
            if q.corridor_half_width_h and gx > q.corridor_half_width_h * (c.cy + c.size
                                                                           - foe[1]):
                continue
            d = 0.0
            if q.select == "nearest_foe":
                gy = max(0.0, abs(c.cy - foe[1]) - c.size)
                d = math.sqrt(gx * gx + gy * gy)
            considered += 1
            if not (c.spread <= max_spread and c.tau >= q.min_tau_s
                    and T - c.t_meas <= c.tau * 1e6
                    and math.hypot(c.cx - foe[0], c.cy - foe[1]) <= c.tau * q.max_speed_pxs):
                continue
            credible += 1
            if fb is None or d < fb[0] or (d == fb[0] and a > fb[1]):
                fb = (d, a, k)
            if use_ground and not (c.rho < 1.0 - q.ground_tolerance):
                continue
            if q.select_hold and c.id == held:
                held_k = k
            if best is None or d < best[0] or (d == best[0] and a > best[1]):
                best = (d, a, k)
        if held_k is not None:
            best = (0.0, slots[held_k].activity_at(T, q.activity_tau_ms * 1000.0), held_k)
        if best is None and (q.ground_fallback or not use_ground):
            best = fb
        held = -1 if best is None else slots[best[2]].id
        if best is not None:
            c = slots[best[2]]
            ttc_rows.append((T, c.tau, c.id, *c.position(), best[1]))
        else:
            reasons["no_foe" if foe is None else "no_cluster" if not considered
                    else "not_credible" if not credible else "on_road"] += 1

    def estimate(c, T, k_now):
        recent = [s for s in c.samples if T - s[0] <= q.sample_max_age_ms * 1000.0]
        if len(recent) >= q.min_samples and k_now > 0.0:
            c.rho = median([s[2] for s in recent]) / k_now
        taus = [s[1] - (T - s[0]) * 1e-6 for s in recent]
        if c.tau is not None:  # tau falls 1 s per s
            dt = (T - c.t_tau) * 1e-6
            c.tau -= dt
            c.var += q.process_noise_s2_per_s * dt
            c.t_tau = T
        if len(taus) < q.min_samples:
            return
        med = median(taus)
        agree = [s for s in recent if abs(s[1] - (T - s[0]) * 1e-6 - med) <= AGREEMENT * med]
        if agree:
            c.mx, c.my = median([s[3] for s in agree]), median([s[4] for s in agree])
        if len(agree) >= q.min_samples and k_now > 0.0:
            c.rho = median([s[2] for s in agree]) / k_now
        mad = median([abs(v - med) for v in taus])
        c.spread = 1.4826 * mad / med if med > 0.0 else math.inf
        c.t_meas = max(s[0] for s in c.samples)
        sigma = 1.4826 * mad / math.sqrt(len(taus)) + q.rel_noise_floor * abs(med)
        r = sigma * sigma + 1e-12
        if c.tau is None:
            c.tau, c.var, c.t_tau, c.misses = med, r, T, 0
            return
        innov = med - c.tau
        s = c.var + r
        if innov * innov > q.gate_sigma ** 2 * s:
            c.misses += 1
            if c.misses >= 3:
                c.tau, c.var, c.misses = med, r, 0
            return
        c.misses = 0
        gain = c.var / s
        c.tau += gain * innov
        c.var = (1.0 - gain) * c.var

    def add_event(px, py, ti, tau):
        nonlocal next_id
        kg = tau * (py - foe[1])
        near = free = None
        for k, c in enumerate(slots):
            if c is None:
                free = k if free is None else free
                continue
            a = c.activity_at(ti, q.activity_tau_ms * 1000.0)
            if a < q.min_activity and free is None:
                free = k
            d = max(abs(px - c.cx), abs(py - c.cy))
            if d <= c.size + q.join_margin_px and (near is None or d < near[1]):
                near = (k, d)
        if near is None and free is None:
            reasons["no_slot"] += 1
            return
        if near is None:
            k = free
            c = slots[k] = Cluster(next_id, px, py, ti, q.cluster_size_px, q.samples_per_cluster)
            next_id += 1
        else:
            k, d = near
            c = slots[k]
            a = c.activity_at(ti, q.activity_tau_ms * 1000.0) + 1.0
            c.activity, c.t_last = a, float(ti)
            if d > c.size:
                c.size = min(q.max_cluster_size_px, d)
            c.cx += (px - c.cx) / a
            c.cy += (py - c.cy) / a
        c.samples.append((float(ti), tau, kg, px, py))
        if not (c.rho < 1.0 - q.ground_tolerance):
            votes_kg.append(kg)
            votes_t.append(float(ti))

    def tau_of(px, py, vx, vy, pol, ti, ta):
        sp = math.sqrt(vx * vx + vy * vy)
        rot = 0.0
        if f and sp > 0:
            rot = rotational_speed_naive(px, py, vx / sp, vy / sp, omega, f, cx, cy)
        tx, ty = (vx * (1 - rot / sp), vy * (1 - rot / sp)) if rot else (vx, vy)
        tau = float(event_tau_naive([px], [py], [tx], [ty], foe[0], foe[1],
                                    q.region_b_half_width_px, q.region_b_min_below_px,
                                    q.min_distance_px, q.min_speed_pxs, q.max_speed_pxs,
                                    q.min_tau_s, q.max_tau_s)[0])
        if tau > 0.0 and q.baseline_px > 0:
            d0 = (px - foe[0]) * vx / sp + (py - foe[1]) * vy / sp
            # the rotation's displacement along n between tq and the arrival ta: the angle
            # turned where the rotation is measured, else the latest rotational speed x time
            def shift_of(tq):
                if f and measured:
                    turned = angle_naive(angles, ta, omega) - angle_naive(angles, tq, omega)
                    return rotational_speed_naive(px, py, vx / sp, vy / sp, turned, f, cx, cy)
                return rot * (ta - tq) * 1e-6
            # compared at the edge's arrival at p, then moved forward to the event's time
            tau = baseline_tau_naive(last_t[pol], px, py, vx / sp, vy / sp, d0, float(ta),
                                     q.baseline_px, q.baseline_max_ms * 1000.0,
                                     q.baseline_width_px, shift_of)
            if tau > 0.0:
                tau -= (ti - ta) * 1e-6
            if tau < q.min_tau_s or tau > q.max_tau_s:
                tau = -1.0
        return tau

    for pk in packets:
        if tick is None:
            tick = -(-pk.t_start // period) * period
        entries = []
        series = pk.series.get("foe")
        if series is not None:
            w = np.radians(np.stack([series[c] for c in ("wx_deg_s", "wy_deg_s", "wz_deg_s")],
                                    1).astype(np.float64))
            w[series["rotation"] == 0] = 0.0
            entries = [(int(a), float(b), float(c), wa, bool(r == 2)) for a, b, c, wa, r in
                       zip(series["t"], series["x"], series["y"], w, series["rotation"],
                           strict=True)]
        for i in range(len(pk.t)):
            ti = int(pk.t[i])
            while tick <= ti:
                do_tick(float(tick))
                tick += period
            apply_foe(entries, ti)
            px, py = float(pk.x[i]), float(pk.y[i])
            vx, vy = float(pk.vx[i]), float(pk.vy[i])
            pol = 1 if pk.p[i] > 0 else 0
            # the edge's arrival: its pixel's run start, unless the run spans more than
            # edge_run_px px of the edge's motion
            ta = int(pk.t_edge[i])
            if (ti - ta) * 1e-6 * math.sqrt(vx * vx + vy * vy) > q.edge_run_px:
                ta = ti
            if foe is not None:
                tau = tau_of(px, py, vx, vy, pol, ti, ta)
                if tau > 0.0:
                    add_event(px, py, ti, tau)
            if q.baseline_px > 0 and 0 <= pk.x[i] < width and 0 <= pk.y[i] < height:
                last_t[pol, pk.y[i], pk.x[i]] = ta
        while tick < pk.t_end:
            do_tick(float(tick))
            tick += period
        apply_foe(entries, math.inf)
    if no_ttc is not None:
        no_ttc.update(reasons)
    return ttc_rows, cluster_rows


def _bin(kg, k_min=0.01, width=0.02) -> int:
    """The ground histogram's bin of kg > 0."""
    return int(math.floor((math.log(kg) - math.log(k_min)) / width))
