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


class RollingCamera:
    """A camera rolling about its optical axis in front of a pinwheel of ``sectors`` equal
    black and white sectors centred on it: the image turns about ``centre`` at
    ``-omega_z(t)``, ``omega_z(t) = w0 + amp sin(2 pi t / period)`` rad/s (constant sign).

    :meth:`events` gives one event per pixel and sector edge crossing, at the exact time (µs,
    floored), ON where a white sector arrives; :meth:`imu` the camera's IMU series (gyro with
    ``bias_dps`` added and stamped ``offset_us`` late, optional Gaussian noise; the
    accelerometer sees gravity turning in the image plane, upright at t = 0); :meth:`flow` the
    true flow.
    """

    def __init__(self, geometry: Geometry = Geometry(80, 60), centre=(44.0, 27.0),
                 w0: float = 1.2, amp: float = 0.6, period_s: float = 0.5,
                 duration_us: int = 1_500_000, sectors: int = 16):
        if abs(amp) >= abs(w0):
            raise ValueError("the roll rate must keep its sign: |amp| < |w0|")
        self.geometry, self.centre = geometry, (float(centre[0]), float(centre[1]))
        self.w0, self.amp, self.period_s = w0, amp, period_s
        self.duration_us, self.sectors = int(duration_us), int(sectors)

    def omega_z(self, t_us) -> np.ndarray:
        t = np.asarray(t_us, np.float64) * 1e-6
        return self.w0 + self.amp * np.sin(2 * np.pi * t / self.period_s)

    def angle(self, t_us) -> np.ndarray:
        """The roll so far, rad: the integral of omega_z from 0."""
        t = np.asarray(t_us, np.float64) * 1e-6
        T = self.period_s
        return self.w0 * t + self.amp * T / (2 * np.pi) * (1 - np.cos(2 * np.pi * t / T))

    def flow(self, x, y, t_us):
        w = self.omega_z(t_us)
        return (w * (np.asarray(y, np.float64) - self.centre[1]),
                -w * (np.asarray(x, np.float64) - self.centre[0]))

    def events(self) -> EventPacket:
        g = self.geometry
        K = self.sectors
        s = 1.0 if self.w0 > 0 else -1.0
        grid = np.arange(0, self.duration_us + 10, 10, dtype=np.float64)
        psi = s * self.angle(grid)                     # increasing
        ys, xs = np.mgrid[0:g.height, 0:g.width].astype(np.float64)
        keep = np.hypot(xs - self.centre[0], ys - self.centre[1]) >= 2.0
        xs, ys = xs[keep], ys[keep]
        phi = np.arctan2(ys - self.centre[1], xs - self.centre[0])
        step = 2 * np.pi / K
        first = np.mod(-s * phi, step)                 # the first edge to cross each pixel
        n_cross = np.floor((psi[-1] - first) / step).astype(np.int64) + 1
        n_cross = np.maximum(n_cross, 0)
        pix = np.repeat(np.arange(len(xs)), n_cross)
        m = np.arange(len(pix)) - np.repeat(np.cumsum(n_cross) - n_cross, n_cross)
        target = first[pix] + m * step
        t = np.floor(np.interp(target, psi, grid)).astype(np.int64)
        sector = np.rint((target + s * phi[pix]) / step).astype(np.int64)
        ok = t < self.duration_us
        order = np.lexsort((pix[ok], t[ok]))
        x = xs[pix[ok]][order].astype(np.uint16)
        y = ys[pix[ok]][order].astype(np.uint16)
        p = np.where(sector[ok][order] % 2 == 0, 1, -1).astype(np.int8)
        return EventPacket(geometry=g, t_start=0, t_end=self.duration_us, x=x, y=y,
                           t=t[ok][order], p=p)

    def imu(self, rate_hz: float = 1000.0, offset_us: float = 0.0,
            bias_dps=(0.0, 0.0, 0.0), noise_dps: float = 0.0, seed: int = 0) -> np.ndarray:
        from evchain.core.series import IMU

        rng = np.random.default_rng(seed)
        t = np.arange(0, self.duration_us, 1e6 / rate_hz).astype(np.int64)
        n = len(t)
        wz = np.degrees(self.omega_z(t - offset_us))
        noise = rng.normal(0.0, noise_dps, (n, 3)) if noise_dps else np.zeros((n, 3))
        up = -np.pi / 2 - self.angle(t)               # gravity turns against the roll
        return IMU.array(t=t, ax=np.cos(up), ay=np.sin(up), az=np.zeros(n),
                         gx=bias_dps[0] + noise[:, 0], gy=bias_dps[1] + noise[:, 1],
                         gz=wz + bias_dps[2] + noise[:, 2], temperature_c=np.full(n, 30.0))
