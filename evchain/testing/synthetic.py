"""Synthetic streams with known answers, for tests, the contract suite and benchmarks.

All generators are deterministic given ``seed`` and return packets that pass ``validate()``.
"""

from __future__ import annotations

import numpy as np

from evchain.core.packets import EventPacket, FlowPacket, FramePacket, Geometry


def random_events(n: int, geometry: Geometry = Geometry(64, 48), t_start: int = 0,
                  t_end: int = 100_000, seed: int = 0) -> EventPacket:
    """``n`` uniformly random events in ``[t_start, t_end)``, time-sorted."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t_start, t_end, n)).astype(np.int64)
    return EventPacket(geometry=geometry, t_start=t_start, t_end=t_end,
                       x=rng.integers(0, geometry.width, n).astype(np.uint16),
                       y=rng.integers(0, geometry.height, n).astype(np.uint16),
                       t=t, p=rng.choice(np.array([-1, 1], np.int8), n))


def moving_edge_events(vx_pxs: float, vy_pxs: float, geometry: Geometry = Geometry(64, 48),
                       duration_us: int = 200_000, polarity: int = 1,
                       offset_px: float = 0.0) -> EventPacket:
    """A straight edge moving with velocity (vx, vy) px/s; each pixel fires once, exactly when
    the edge line passes its centre. The edge's normal is the velocity direction, so the true
    normal flow equals (vx, vy) everywhere.

    The edge starts through the point ``c - n * (extent + offset_px)`` where c is the image centre
    and n the unit normal, so it sweeps across the whole image if the duration allows.
    """
    speed = float(np.hypot(vx_pxs, vy_pxs))
    if speed <= 0:
        return EventPacket.empty(geometry, 0, duration_us)
    nx, ny = vx_pxs / speed, vy_pxs / speed
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width]
    extent = 0.5 * np.hypot(geometry.width, geometry.height)
    d = (xs - geometry.cx) * nx + (ys - geometry.cy) * ny + extent + offset_px
    t = d / speed * 1e6
    keep = (t >= 0) & (t < duration_us)
    order = np.lexsort((xs[keep], ys[keep], np.floor(t[keep])))
    tt = np.floor(t[keep]).astype(np.int64)[order]
    n = len(tt)
    return EventPacket(geometry=geometry, t_start=0, t_end=duration_us,
                       x=xs[keep][order].astype(np.uint16), y=ys[keep][order].astype(np.uint16),
                       t=tt, p=np.full(n, polarity, np.int8))


def expansion_flow(foe: tuple[float, float], tau_s: float, n: int,
                   geometry: Geometry = Geometry(128, 96), t_start: int = 0,
                   t_end: int = 100_000, seed: int = 0, normal_only: bool = False,
                   noise_pxs: float = 0.0) -> FlowPacket:
    """Flow events of a pure expansion: v = (p - foe) / tau at random pixels.

    With ``normal_only`` each vector is projected on a random edge normal (what LK and plane
    fitting return); ``noise_pxs`` adds Gaussian noise to each component.
    """
    rng = np.random.default_rng(seed)
    ev = random_events(n, geometry, t_start, t_end, seed)
    vx = (ev.x - foe[0]) / tau_s
    vy = (ev.y - foe[1]) / tau_s
    if normal_only:
        a = rng.uniform(0, np.pi, n)
        nx, ny = np.cos(a), np.sin(a)
        dot = vx * nx + vy * ny
        vx, vy = dot * nx, dot * ny
    if noise_pxs:
        vx = vx + rng.normal(0, noise_pxs, n)
        vy = vy + rng.normal(0, noise_pxs, n)
    return FlowPacket(geometry=geometry, t_start=t_start, t_end=t_end, x=ev.x, y=ev.y, t=ev.t,
                      p=ev.p, vx=vx.astype(np.float32), vy=vy.astype(np.float32))


def textured_frames(n: int, geometry: Geometry = Geometry(64, 48), dt_us: int = 1000,
                    speed_pxs: float = 200.0, t0_us: int = 0, seed: int = 0) -> FramePacket:
    """Frames of a smooth random texture translating right at ``speed_pxs`` (linear intensity
    in [0.05, 1.05])."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(4, 3))
    t = t0_us + dt_us * np.arange(n, dtype=np.int64)
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width].astype(np.float64)
    frames = np.empty((n, *geometry.shape), np.float32)
    for i, ti in enumerate(t):
        u = xs - speed_pxs * ti * 1e-6
        img = sum(np.sin(0.05 * (j + 1) * (k[j, 0] * u + k[j, 1] * ys) + k[j, 2])
                  for j in range(4))
        frames[i] = 0.55 + 0.125 * img
    return FramePacket(geometry=geometry, t_start=int(t[0]), t_end=int(t[-1]) + 1,
                       frames=np.clip(frames, 0.0, None), t=t)


class ExpansionTruth:
    """Ground truth of a pure expansion towards a fixed FOE: the camera approaches a
    fronto-parallel plane without rotating and collides at ``t_collision_s``; flow
    v = (p - foe) / tau(t) with tau(t) = t_collision - t."""

    def __init__(self, foe: tuple[float, float], t_collision_s: float, depth_m: float = 10.0):
        self.foe_xy = foe
        self.t_collision_s = t_collision_s
        self.depth_m = depth_m

    def ttc(self, t_us):
        tau = self.t_collision_s - np.asarray(t_us, np.float64) * 1e-6
        return np.where(tau > 0, tau, np.nan)

    def foe(self, t_us):
        shape = np.shape(t_us)
        return np.full(shape, self.foe_xy[0]), np.full(shape, self.foe_xy[1])

    def angular_velocity(self, t_us):
        z = np.zeros(np.shape(t_us))
        return z, z.copy(), z.copy()

    def flow(self, x, y, t_us):
        tau = self.ttc(t_us)
        return ((np.asarray(x, np.float64) - self.foe_xy[0]) / tau,
                (np.asarray(y, np.float64) - self.foe_xy[1]) / tau)

    def depth(self, x, y, t_us):
        return np.broadcast_to(self.ttc(t_us) / self.t_collision_s * self.depth_m,
                               np.broadcast_shapes(np.shape(x), np.shape(t_us)))


def expansion_stream(n_packets: int = 4, events_per_packet: int = 400,
                     geometry: Geometry = Geometry(128, 96, f=100.0), packet_us: int = 25_000,
                     foe: tuple[float, float] = (70.0, 40.0), t_collision_s: float = 2.0,
                     seed: int = 0, foe_series: bool = False
                     ) -> tuple[list[FlowPacket], ExpansionTruth]:
    """Flow packets of a pure expansion (normal flow on random edge normals) and the matching
    ground truth; with ``foe_series``, each packet carries the true FOE as a ``foe`` series entry
    (t, x, y, support, total) at its start, as ``foe_map`` would provide."""
    from evchain.core.series import FOE

    truth = ExpansionTruth(foe, t_collision_s)
    packets = []
    for i in range(n_packets):
        t0 = i * packet_us
        tau = float(truth.ttc(t0 + packet_us // 2))
        p = expansion_flow(foe, tau, events_per_packet, geometry, t0, t0 + packet_us,
                           seed=seed + i, normal_only=True)
        entry = FOE.array(t=[t0], x=[foe[0]], y=[foe[1]], support=[1.0], total=[1.0])
        packets.append(p.with_series(FOE.name, entry) if foe_series else p)
    return packets, truth


def approach_flow_packets(foe=(60.0, 45.0), tau_s: float = 2.0, n: int = 20000,
                      geometry: Geometry = Geometry(128, 96, f=100.0),
                      duration_us: int = 200_000, n_packets: int = 4, seed: int = 0,
                      normal_only: bool = False, noise_frac: float = 0.0,
                      outlier_frac: float = 0.0, tau_shrinks: bool = False) -> list[FlowPacket]:
    """Flow events of a pure expansion v = (p - foe) / tau at random pixels, cut into
    ``n_packets`` packets (foe_map / ttc tests and benchmarks).

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
