"""Brute-force O(pixels) reference of the ``foe_map`` kernel, and an expansion-flow generator."""

from __future__ import annotations

import math

import numpy as np

from evchain.core.packets import FlowPacket, Geometry
from evchain.testing.synthetic import approach_flow_packets


def region_mask(geometry: Geometry, radius_px: float | None) -> np.ndarray:
    """Boolean [H, W]: cells of region A (centre inside the disc, or everything)."""
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width]
    if radius_px is None:
        return np.ones(geometry.shape, bool)
    return (xs - geometry.cx) ** 2 + (ys - geometry.cy) ** 2 <= radius_px ** 2


def brute_map(x, y, t, vx, vy, accepted, T, tau_us, mask, vote_w=None) -> np.ndarray:
    """Map value of every cell at time T: sum of vote_w[i] * exp(-(T - t_i)/tau) over accepted
    events with t_i < T whose half-plane {q: (p - q).v > 0} holds the cell (q: integer cell
    coordinates; x, y in the same coordinates). NaN outside region A."""
    H, W = mask.shape
    qy, qx = np.mgrid[0:H, 0:W].astype(np.float64)
    m = np.zeros((H, W))
    for i in range(len(t)):
        if not accepted[i] or t[i] >= T:
            continue
        px, py = float(x[i]), float(y[i])
        fvx, fvy = float(vx[i]), float(vy[i])
        inside = (px - qx) * fvx + (py - qy) * fvy > 0.0
        m += inside * math.exp(-(T - t[i]) / tau_us) * (1.0 if vote_w is None else vote_w[i])
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


def cells(packet: FlowPacket, radius_px: float | None, cell_px: int):
    """(geometry in cells, radius in cells, x, y in cell coordinates): cell c covers pixels
    cell_px * c .. cell_px * c + cell_px - 1, its centre is the integer c."""
    g = packet.geometry
    if cell_px == 1:
        return g, radius_px, packet.x, packet.y
    h = 0.5 * (cell_px - 1)
    gc = Geometry(-(-g.width // cell_px), -(-g.height // cell_px), cx=(g.cx - h) / cell_px,
                  cy=(g.cy - h) / cell_px)
    return (gc, None if radius_px is None else radius_px / cell_px,
            (packet.x.astype(np.float64) - h) / cell_px,
            (packet.y.astype(np.float64) - h) / cell_px)


def foe_naive(packet: FlowPacket, tau_ms: float, radius_px: float | None, period_us: int,
              refine_fraction: float, min_speed_pxs: float = 0.0,
              max_angle_deg: float | None = None, speed_weight_pxs: float | None = None,
              cell_px: int = 1):
    """Estimates (t, x, y, support) of one packet processed from a fresh state (x, y in pixels;
    the map and the angular gate's 1-unit dead zone work in cells)."""
    g, radius_px, xs, ys = cells(packet, radius_px, cell_px)
    mask = region_mask(g, radius_px)
    tau_us = tau_ms * 1000.0
    vx = packet.vx.astype(np.float64)
    vy = packet.vy.astype(np.float64)
    s2 = vx * vx + vy * vy
    vote_w = None
    if speed_weight_pxs:
        vote_w = speed_weight_pxs / (speed_weight_pxs + np.sqrt(s2))
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
                m = brute_map(xs, ys, packet.t, vx, vy, accepted, T, tau_us, mask, vote_w)
                ex, ey, best = estimate(m, refine_fraction)
                if best > 0:
                    est = (ex, ey)
                    h = 0.5 * (cell_px - 1)
                    out.append((T, ex * cell_px + h, ey * cell_px + h, best))
            T += period_us
        if i >= n:
            break
        ok = s2[i] > 0 and s2[i] >= min_speed_pxs ** 2
        if ok and max_angle_deg is not None and est is not None:
            rx, ry = xs[i] - est[0], ys[i] - est[1]
            rn = math.hypot(rx, ry)
            if rn > 1.0:
                c = (rx * vx[i] + ry * vy[i]) / (rn * math.sqrt(s2[i]))
                ok = c >= math.cos(math.radians(max_angle_deg))
        accepted[i] = ok
        i += 1
    return np.array(out).reshape(-1, 4)


# the generator lives in evchain.testing.synthetic (benchmarks use it too)
expansion_packets = approach_flow_packets
