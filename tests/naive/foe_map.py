"""Brute-force O(pixels) reference of the ``foe_map`` kernel, and an expansion-flow generator."""

from __future__ import annotations

import math

import numpy as np

from evchain.core.packets import FlowPacket, Geometry


def region_mask(geometry: Geometry, radius_px: float | None) -> np.ndarray:
    """Boolean [H, W]: cells of region A (centre inside the disc, or everything)."""
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width]
    if radius_px is None:
        return np.ones(geometry.shape, bool)
    return (xs - geometry.cx) ** 2 + (ys - geometry.cy) ** 2 <= radius_px ** 2


def brute_map(x, y, t, vx, vy, accepted, T, tau_us, mask) -> np.ndarray:
    """Map value of every cell at time T: sum of exp(-(T - t_i)/tau) over accepted events with
    t_i < T whose half-plane {q: (p - q).v > 0} holds the cell. NaN outside region A."""
    H, W = mask.shape
    qy, qx = np.mgrid[0:H, 0:W].astype(np.float64)
    m = np.zeros((H, W))
    for i in range(len(t)):
        if not accepted[i] or t[i] >= T:
            continue
        px, py = float(x[i]), float(y[i])
        fvx, fvy = float(vx[i]), float(vy[i])
        inside = (px - qx) * fvx + (py - qy) * fvy > 0.0
        m += inside * math.exp(-(T - t[i]) / tau_us)
    m[~mask] = np.nan
    return m


def estimate(m: np.ndarray, refine_fraction: float):
    """(x, y, max) of a map: refined centroid of the near-maximal cells (as the kernel)."""
    best = np.nanmax(m)
    worst = np.nanmin(m)
    if refine_fraction > 0:
        thr = best - refine_fraction * (best - worst)
    else:
        thr = best - 1e-12 * abs(best)
    sel = np.nan_to_num(m, nan=-np.inf) >= thr
    ys, xs = np.nonzero(sel)
    if refine_fraction > 0 and best > thr:
        w = m[sel] - thr
    else:
        w = np.ones(len(xs))
    return float((w * xs).sum() / w.sum()), float((w * ys).sum() / w.sum()), float(best)


def foe_naive(packet: FlowPacket, tau_ms: float, radius_px: float | None, period_us: int,
              refine_fraction: float, min_speed_pxs: float = 0.0,
              max_angle_deg: float | None = None):
    """Estimates (t, x, y, support) of one packet processed from a fresh state."""
    g = packet.geometry
    mask = region_mask(g, radius_px)
    tau_us = tau_ms * 1000.0
    vx = packet.vx.astype(np.float64)
    vy = packet.vy.astype(np.float64)
    s2 = vx * vx + vy * vy
    accepted = np.zeros(len(packet), bool)
    out = []
    est = None
    T = -(-packet.t_start // period_us) * period_us
    i = 0
    n = len(packet)
    while True:
        t_next = packet.t[i] if i < n else packet.t_end
        while T < t_next or (i < n and T == t_next):
            if accepted[:i].any():
                m = brute_map(packet.x, packet.y, packet.t, vx, vy, accepted, T, tau_us, mask)
                ex, ey, best = estimate(m, refine_fraction)
                if best > 0:
                    est = (ex, ey)
                    out.append((T, ex, ey, best))
            T += period_us
        if i >= n:
            break
        ok = s2[i] > 0 and s2[i] >= min_speed_pxs ** 2
        if ok and max_angle_deg is not None and est is not None:
            rx, ry = packet.x[i] - est[0], packet.y[i] - est[1]
            rn = math.hypot(rx, ry)
            if rn > 1.0:
                c = (rx * vx[i] + ry * vy[i]) / (rn * math.sqrt(s2[i]))
                ok = c >= math.cos(math.radians(max_angle_deg))
        accepted[i] = ok
        i += 1
    return np.array(out).reshape(-1, 4)


def expansion_packets(foe=(60.0, 45.0), tau_s: float = 2.0, n: int = 20000,
                      geometry: Geometry = Geometry(128, 96, f=100.0),
                      duration_us: int = 200_000, n_packets: int = 4, seed: int = 0,
                      normal_only: bool = False, noise_frac: float = 0.0,
                      outlier_frac: float = 0.0, tau_shrinks: bool = False) -> list[FlowPacket]:
    """Flow of a pure expansion v = (p - foe) / tau at random pixels, cut into packets.

    ``normal_only`` projects each vector on a random edge normal; ``noise_frac`` adds Gaussian
    noise of that fraction of the local speed to each component; ``outlier_frac`` replaces that
    share of vectors by random ones; ``tau_shrinks`` makes tau fall at 1 s/s (approach) so that
    tau(t) = tau_s - t.
    """
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, duration_us, n)).astype(np.int64)
    x = rng.integers(0, geometry.width, n)
    y = rng.integers(0, geometry.height, n)
    tau = tau_s - t * 1e-6 if tau_shrinks else np.full(n, tau_s)
    vx = (x - foe[0]) / tau
    vy = (y - foe[1]) / tau
    if normal_only:
        a = rng.uniform(0, np.pi, n)
        nx, ny = np.cos(a), np.sin(a)
        dot = vx * nx + vy * ny
        vx, vy = dot * nx, dot * ny
    if noise_frac:
        sp = np.hypot(vx, vy)
        vx = vx + rng.normal(0, 1, n) * noise_frac * sp
        vy = vy + rng.normal(0, 1, n) * noise_frac * sp
    if outlier_frac:
        bad = rng.random(n) < outlier_frac
        vx[bad] = rng.normal(0, 30, bad.sum())
        vy[bad] = rng.normal(0, 30, bad.sum())
    edges = np.linspace(0, duration_us, n_packets + 1).astype(np.int64)
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        k = (t >= a) & (t < b)
        out.append(FlowPacket(geometry=geometry, t_start=int(a), t_end=int(b),
                              x=x[k].astype(np.uint16), y=y[k].astype(np.uint16), t=t[k],
                              p=np.ones(k.sum(), np.int8), vx=vx[k].astype(np.float32),
                              vy=vy[k].astype(np.float32)))
    return out
