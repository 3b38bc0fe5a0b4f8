"""``foe_fit``: the FOE (the heading) and the camera's rotation from normal-flow magnitudes with a
piecewise-planar scene model."""

from __future__ import annotations

import math
import statistics
from collections import deque
from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.camera_scale import REFERENCE_FOCAL_PX, derived, px_scale
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.series import FOE, FOE_VOTES
from evchain.errors import DataError
from evchain.imu.gyro import GyroTrack

_COLUMNS = ("x", "y", "nx", "ny", "s", "e", "c0", "c1", "c2")
#: rotation_source imu: the gyro's rate is averaged over each slab at this many times
GYRO_POINTS = 16
#: the modes of :class:`FoeFit`: no rotation, or the rotation axis that is free (its index)
LEVEL, PITCHING, TURNING = -1, 0, 1


def _median(values: list) -> float:
    """np.median of a few floats, the same value bit for bit (NaN when one is NaN), without its
    array machinery."""
    return math.nan if any(map(math.isnan, values)) else float(statistics.median(values))


class FoeFit(Filter):
    """Refines the ``foe`` series of ``foe_map`` by fitting the flow speeds of a road and two
    facades seen by a translating and turning camera (robust Gauss-Newton; see
    docs/explanation/foe_ttc.md).

    A road point ``dy`` rows below the FOE (level camera) has inverse time to contact ``a0 dy``,
    a facade point ``dx`` columns beside it ``a1 |dx|`` (left) or ``a2 |dx|`` (right), so its
    normal flow speed is ``(p - foe).n`` times that, plus the normal component of the rotational
    flow of the camera's angular velocity ``w`` (independent of depth; needs the focal length).
    Buildings stand at different setbacks, so each side's scale is times a ratio per depth
    band (``facade_bands`` bands of ``facade_band_depth`` times the facade's lateral
    distance), refitted after every fit and tied to 1 by ``facade_band_prior``.
    Every ``estimate_every_us`` the FOE, the scales and ``w`` are fitted jointly to the flow
    events of the last ``3 tau_ms`` (weights decaying with ``tau_ms``, Tukey on the relative
    speed residual), ``w`` constant within each ``estimate_every_us`` of that stretch, and every
    event seen in the camera frame of the fit time, turned by the pitch since its time (a
    car's heading follows its yaw, not its pitch).

    Rotation unknowns are only fitted while the camera turns: normal flow tells a yaw from a
    sideways shift of the FOE only poorly (both move the image sideways), and a pitch from a
    shift of the horizon; an axis fitted while it does not turn gives the flow's errors a way
    to move the FOE. The fit runs in one of three modes. *Level* (the start): no rotation, the
    FOE from the flow. *Pitching*: pitch free. *Turning*: yaw free, pitch held (under fast yaw
    the flow's errors pass for pitch) and the FOE's column held at the median of the settled
    level (or pitching) fits over the last ``heading_memory_s`` before the turn (a car's heading
    stays fixed in its camera). After each fit the newest ``estimate_every_us`` is refitted
    with every axis free (the probe); once the fits have run warm for 3 ``tau_ms``, the mode
    turns to turning (first) or pitching when the median of the last 5 probes turns about that
    axis faster than ``rotation_threshold_deg_s``, and back to level once that axis stayed
    below it for 3 ``tau_ms``. A car's body pitches about its rest angle, so pitching is
    entered and kept only while the probes' mean pitch rate over the last ``heading_memory_s``
    stays below the threshold: a pitch of one sign that lasts is the flow of a ground plane
    whose FOE row is off (normal flow on a plane tells the two apart poorly), not the camera.
    The first pitching fit starts from scratch at the level fit's FOE (a gear shift's first
    slabs are outliers at pitch 0 to a warm fit) and is kept if it explains more than the
    level fit; so does a pitching fit that competes with the votes' fit when the level fit
    would fall back to the votes while the probes call for pitch: if it explains more, the
    mode is pitching, also within 3 ``tau_ms`` of a cold start (a gear shift there pulls the
    votes up and the level fit off).
    Likewise a yaw can be the flow of a ground plane whose FOE column is off: turning is
    entered only when the turning fit's decayed inlier weight exceeds that of a level fit
    (column free, no yaw) by more than ``turn_gain`` (a yaw moves near and far points alike, a
    column shift in proportion to their inverse time to contact); while turning the level fit
    is kept alongside and takes over once the turning fit no longer explains more.
    Roll is not fitted (held at 0).
    With ``rotation_source`` imu the rotation is the gyro's instead (series ``imu``: each
    slab's mean rate, less ``gyro_bias_dps``), from the first fit on, and only the FOE and the
    scales are fitted; while the gyro yaws faster than ``rotation_threshold_deg_s`` the FOE's
    column is held as in the turning mode (the median of the settled fits over the last
    ``heading_memory_s``), until 3 ``tau_ms`` after the yaw fell below it.

    The road's scale ``a0 = V / (f h)`` changes only with the car's speed. As an obstacle
    fills the lower view its rows (a fronto-parallel surface, one inverse time to contact)
    fit the road model with a higher FOE row and a smaller scale, and near contact the road
    below it no longer pins the row. So a fit whose road scale falls below
    ``min_road_scale_ratio`` times the median of the fits over the last ``heading_memory_s``
    while its FOE row rises above theirs is refitted with the FOE's row and the road's scale
    held at those medians (the rest free), and the fits stay held while the free fit's row
    stays above the held one.

    Each fit starts from the previous one, else from the latest ``foe_map`` estimate. When the
    fit fails (singular, fewer than ``min_inliers`` decayed inliers, or farther than
    ``max_deviation_px`` from the voting estimate, in what it is free to move, while a fit
    started from the votes explains more of the flow: a larger decayed inlier weight) the
    voting estimate is emitted and the next fit starts from it again. The ``foe_map`` entries
    move to series ``foe_votes``; series ``foe`` gets one entry per fit (t, x, y, support =
    decayed inlier weight, total = decayed weight of modelled events, the angular velocity wx,
    wy, wz of the latest ``estimate_every_us`` in deg/s, 0 on an axis the mode holds, and
    ``rotation`` 1, or 2 when it is the gyro's; 0 and ``rotation`` 0 when the votes are
    emitted or the geometry has no focal length).

    A fit needs a voting estimate at most ``tau_ms`` old: with none yet, or none for longer
    (``foe_map`` withholds its estimates while the flow's directions agree no better than
    noise would, and the speeds of such flow can still give a fit enough inliers) there is no
    fit and no entry; the fits resume from the last one when voting estimates return.
    ``metrics.foe_fit`` counts the fit times, the fits kept, the voting estimates emitted
    instead, and the times without an estimate.
    """

    name = "foe_fit"
    consumes = FlowPacket
    produces = FlowPacket
    needs_series = (FOE,)
    adds_series = (FOE, FOE_VOTES)

    class Params(FilterParams):
        rotation_source: Literal["flow", "imu"] = Field(
            "flow", description="where the camera's rotation comes from: fitted to the flow "
            "(flow), or the gyro of the series imu (imu: a DAVIS camera's IMU, or the "
            "simulated one of scene.imu_rate_hz), each slab's rotation the gyro's mean rate "
            "over it, less gyro_bias_dps; then only the FOE and the scales are fitted")
        gyro_bias_dps: tuple[float, float, float] = Field(
            (0.0, 0.0, 0.0), description="rotation_source imu: the gyro's bias, deg/s (x, y, "
            "z in the camera's axes), subtracted from its readings")
        tau_ms: float = Field(200.0, gt=0, description="decay time constant of the events' "
                              "weights; events older than 3 tau are dropped")
        estimate_every_us: int = Field(10000, ge=1, description="period of the fits; the "
                                       "camera's rotation is constant within each such "
                                       "stretch of the fitted events")
        rotation_threshold_deg_s: float = Field(
            3.0, gt=0, description="pitch or yaw is fitted from when the newest rotation "
            "refitted with every axis free turns about it faster than this, until it stayed "
            "below for 3 tau (else it is held at 0)")
        heading_memory_s: float = Field(
            0.5, gt=0, description="while turning the FOE's column is held at the median of "
            "the fits over this last stretch before the turn; the road's row and scale are "
            "compared with (and held at) their medians over this last stretch")
        margin_px: float | None = Field(
            None, ge=0, description="events closer than this to a plane's vanishing line (the "
            "FOE's row or column) are left out of that plane, px; null: 10 px x f / 380.6 px "
            "(1.5 deg of view; 10 px on the reference camera, camera_scale.px_scale)")
        tolerance: float = Field(0.25, gt=0, description="Tukey constant on the relative "
                                 "speed residual |s - predicted| / predicted (with a looser "
                                 "one an approaching obstacle's lower rows fit the road and "
                                 "pull the FOE up as it fills the view)")
        max_iter: int = Field(4, ge=1, description="Gauss-Newton iterations per fit")
        max_deviation_px: float | None = Field(
            None, gt=0, description="a fit farther than this from the voting estimate is "
            "checked against a fit started from the votes and falls back to them if that one "
            "has the larger inlier weight (the votes can err by tens of px for seconds), px; "
            "null: 40 px x f / 380.6 px")
        min_inliers: float = Field(50.0, ge=0, description="fall back when the decayed "
                                   "inlier weight is below this")
        facade_bands: int = Field(
            16, ge=0, description="depth bands per facade, each with its own scale (buildings "
            "at other setbacks): a ratio to the side's scale, refitted after each fit and tied "
            "to 1 by facade_band_prior; 0: one scale per side")
        facade_band_depth: float = Field(
            0.5, gt=0, description="depth extent of a facade band in units of the facade's "
            "lateral distance: an event |dx| px beside the FOE is in band "
            "floor(f / (facade_band_depth |dx|))")
        facade_band_prior: float = Field(
            20.0, ge=0, description="decayed event weight that ties each band's scale ratio "
            "to 1 (a ridge: a band with fewer events keeps the side's scale)")
        turn_gain: float = Field(
            0.2, ge=0, description="the turning mode is entered only when its fit's decayed "
            "inlier weight exceeds that of the level fit (FOE column free, no yaw) by more than "
            "this share, and left once it no longer exceeds it (else the yaw is a sideways "
            "shift of the FOE)")
        min_road_scale_ratio: float = Field(
            0.97, ge=0, le=1, description="a fit whose road scale (the speed over the camera's "
            "height) falls below this share of the median over the last heading_memory_s while "
            "its FOE row rises is an obstacle's rows fitted as road: the FOE's row and the "
            "road's scale are held at their medians (0: never)")

    def reset(self) -> None:
        from evchain.kernels import foe_fit as k

        p = self.params
        self._geometry: Geometry | None = None
        self._prm = None
        self._buf = {c: np.zeros(0, np.float64) for c in _COLUMNS}
        self._tref = 0  # e = exp((t - tref) / tau): the decay weights, computed once per event
        self._t = np.zeros(0, np.int64)
        self._lo = self._hi = 0  # the buffer's live events: [lo, hi)
        self._next: int | None = None
        self._th = k.initial_theta(math.nan, math.nan, p.facade_bands)
        self._vote: tuple[int, float, float] | None = None
        self._won = -math.inf  # time a far fit last beat a fit started from the votes
        n_slabs = math.ceil(3 * p.tau_ms * 1000.0 / p.estimate_every_us) + 1
        self._om = np.zeros((n_slabs, 3))  # rotation Om = f w per slab (px/s), latest first
        self._om_t: int | None = None  # the fit time of _om
        self._mode = LEVEL
        self._probes: deque[np.ndarray] = deque(maxlen=5)  # the latest probed rotations, px/s
        self._pitch_probes: deque[tuple[int, float]] = deque()  # (t, probed pitch) over memory
        self._moved = -math.inf  # last time the mode's axis turned faster than the threshold
        self._level_x: deque[tuple[int, float]] = deque()  # (t, FOE column) of settled fits
        self._held_x = math.nan  # the FOE column while turning
        self._level_fit = None  # (th, om) of the level fit kept alongside while turning
        self._road: deque[tuple[int, float, float]] = deque()  # (t, FOE row, road scale)
        self._road_held: tuple[float, float] | None = None  # (FOE row, road scale) held
        self._warm_since: int | None = None  # time of the first fit since the last cold start
        self._counts = {"fit times": 0, "fits": 0, "votes": 0, "no voting estimate": 0}
        if p.rotation_source == "imu":
            self._counts["slabs without gyro"] = 0
        self._gyro = GyroTrack()

    def _start(self, geometry: Geometry) -> None:
        from evchain.kernels import foe_fit as k
        from evchain.kernels.records import record

        p = self.params
        self._geometry = geometry
        self._rotation = geometry.f is not None
        self._imu = p.rotation_source == "imu"
        if self._imu and not self._rotation:
            raise DataError(f"{self.id}: rotation_source imu needs the camera's focal length "
                            "(the geometry has none)")
        scale = px_scale(geometry)
        self._max_deviation = derived(p.max_deviation_px, 40.0, geometry)
        # a Gauss-Newton step moves the FOE by at most 3 px, and a fit has converged once it
        # moves less than 0.05 px (on the reference camera)
        self._prm = record(k.FitParams, margin=derived(p.margin_px, 10.0, geometry),
                           tolerance=p.tolerance, max_iter=p.max_iter, max_step=3.0 * scale,
                           min_step=0.05 * scale, slab_us=p.estimate_every_us,
                           f=geometry.f if self._rotation else 1.0, cx=geometry.cx,
                           cy=geometry.cy,
                           band_px=derived(None, REFERENCE_FOCAL_PX, geometry)
                           / p.facade_band_depth,
                           band_prior=p.facade_band_prior)
        self._turn_pxs = math.radians(p.rotation_threshold_deg_s) * self._prm.f

    def process(self, packet: FlowPacket) -> FlowPacket:
        if not isinstance(packet, FlowPacket):
            raise DataError(f"foe_fit needs a FlowPacket, got {type(packet).__name__}")
        from evchain.kernels import foe_fit as k

        if self._geometry is None:
            self._start(packet.geometry)
        elif packet.geometry is not self._geometry and packet.geometry != self._geometry:
            raise DataError(f"foe_fit: sensor geometry changed from {self._geometry} to "
                            f"{packet.geometry}")
        p = self.params
        period, tau_us = int(p.estimate_every_us), p.tau_ms * 1000.0
        votes = packet.series.get("foe", np.zeros(0, FOE.dtype))
        if self._imu:
            imu = packet.series.get("imu")
            if imu is None and packet.t_end > packet.t_start:  # (a flush's slice is empty)
                raise DataError(f"{self.id}: rotation_source imu needs the series imu in every "
                                "packet (a recording with its IMU, or scene.imu_rate_hz > 0), "
                                f"none in the packet at {packet.t_start} µs")
            if imu is not None:
                self._gyro.append(imu["t"], np.stack([imu["gx"], imu["gy"], imu["gz"]], 1))
            self._gyro.trim(packet.t_start - int(3 * tau_us) - 2 * period)
        if packet.t_end - self._tref > 4 * tau_us:  # keep e within exp(+-4) for the window
            tref = packet.t_end - int(2 * tau_us)
            v = self._buf["e"][self._lo:self._hi]
            v *= math.exp(-(tref - self._tref) / tau_us)
            self._tref = tref
        # the new events' columns, written straight into the buffer after its live events
        n = len(packet)
        hi = self._reserve(n, packet.t_start - int(3 * tau_us))
        b, g = self._buf, self._geometry
        f, cx, cy = (g.f, g.cx, g.cy) if self._rotation else (1.0, 0.0, 0.0)  # (f may be None)
        keep = np.empty(n, np.bool_)
        m = k.flow_columns(packet.x, packet.y, packet.vx, packet.vy, f, cx, cy, self._rotation,
                           b["x"][hi:], b["y"][hi:], b["nx"][hi:], b["ny"][hi:], b["s"][hi:],
                           b["c0"][hi:], b["c1"][hi:], b["c2"][hi:], keep)
        t_new = packet.t if m == n else packet.t[keep]  # the flow stages emit moving events
        np.exp((t_new - self._tref) / tau_us, out=b["e"][hi:hi + m])
        self._t[hi:hi + m] = t_new
        self._hi = hi + m
        if self._next is None:
            self._next = -(-packet.t_start // period) * period
        rows = []
        while self._next < packet.t_end:
            T = self._next
            self._next += period
            j = np.searchsorted(votes["t"], T, side="right")
            if j:
                self._vote = (int(votes["t"][j - 1]), float(votes["x"][j - 1]),
                              float(votes["y"][j - 1]))
            self._counts["fit times"] += 1
            r = None if self._vote is None else self._fit(k, T, tau_us)
            if r is None:
                self._counts["no voting estimate"] += 1
                continue
            rows.append((T, *r))
        out = np.zeros(len(rows), FOE.dtype)
        for i, r in enumerate(rows):
            out[i] = r
        series = dict(packet.series)
        series["foe_votes"] = votes
        series["foe"] = out
        return packet.replace(series=series)

    def _reserve(self, m: int, t_keep: int) -> int:
        """Drop events before ``t_keep`` and make room for ``m`` more after the live ones;
        returns where they go (the live events end there). The arrays grow by doubling and are
        compacted only when full (amortised O(1) per event), in place while the live ones and
        the new ones fill at most half (fresh arrays would cost page faults every time)."""
        lo, hi = self._lo, self._hi
        lo += int(np.searchsorted(self._t[lo:hi], t_keep))
        if hi + m > len(self._t):
            n = hi - lo
            if 2 * (n + m) <= len(self._t):  # then lo > n + m: the copies do not overlap
                for v in (*self._buf.values(), self._t):
                    v[:n] = v[lo:hi]
            else:
                cap = max(2 * (n + m), 1024)
                for c, v in self._buf.items():
                    w = np.empty(cap, np.float64)
                    w[:n] = v[lo:hi]
                    self._buf[c] = w
                tt = np.empty(cap, np.int64)
                tt[:n] = self._t[lo:hi]
                self._t = tt
            lo, hi = 0, n
        self._lo, self._hi = lo, hi
        return hi

    def _index(self, t_us: int) -> int:
        """The first live event at or after ``t_us``."""
        return self._lo + int(np.searchsorted(self._t[self._lo:self._hi], t_us))

    def _free(self) -> np.ndarray:
        """The unknowns of the mode: FOE column, pitch, yaw, roll (:func:`fit`'s ``free``)."""
        if self._imu:    # the rotation is the gyro's; turning holds the column
            return np.array([self._mode != TURNING, False, False, False])
        if self._mode == TURNING:
            return np.array([math.isnan(self._held_x), False, True, False])
        return np.array([True, self._mode == PITCHING, False, False])

    def _fit(self, k, T, tau_us):
        """(x, y, support, total, wx, wy, wz) of the fit at T, or the voting estimate's; None
        when the latest voting estimate is older than tau."""
        p = self.params
        t_vote, vx, vy = self._vote
        if T - t_vote > tau_us:  # the flow has shown no FOE for tau: wait, resume from here
            return None
        new_slabs = self._shift_slabs(T)
        if self._imu:
            self._gyro_slabs(T, new_slabs)
        warm = not math.isnan(self._th[k.FOE_X])
        if not warm:
            self._th = k.initial_theta(vx, vy, p.facade_bands)
        free = self._free()
        if not free[0]:
            self._th[k.FOE_X] = self._held_x
        i0, i1 = self._index(T - int(3 * tau_us)), self._index(T)
        g = math.exp(-(T - self._tref) / tau_us)
        events = k.FitEvents(*(self._buf[c] for c in _COLUMNS), self._t)
        probe = np.zeros(3)

        def run(th, om, axes=free):
            ok, inl, tot = k.fit(events, i0, i1, T, g, th, om, axes, probe, self._prm)
            return ok and inl >= p.min_inliers, inl, tot

        th, om = self._th.copy(), self._om.copy()
        ok, inl, tot = run(th, om)
        found = probe.copy()
        held = self._held_road(th) if ok and warm else None
        if held is not None:  # an obstacle's rows counted as road: the road's row and scale
            free = np.append(free, False)
            th, om = self._th.copy(), self._om.copy()
            th[k.FOE_Y], th[k.ROAD] = held
            ok, inl, tot = run(th, om, free)
            found = probe.copy()
        # a held FOE column or row is not the fit's: only the free ones can run away
        far = math.hypot(th[k.FOE_X] - vx if free[0] else 0.0,
                         th[k.FOE_Y] - vy if held is None else 0.0) > self._max_deviation
        if ok and far and warm:
            # Far from the votes: the votes may be the wrong ones (at 15 m/s they err by 30-50 px
            # for seconds). Refit from them; keep the warm fit unless the votes' fit explains
            # more of the flow (larger decayed inlier weight) or the warm fit is the only one.
            # A warm fit that won stays unchallenged for tau (the window's weights change by
            # 1/e), which keeps the extra fits to a few per cent while the votes are off.
            if T - self._won >= tau_us:
                tv = k.initial_theta(vx, vy, p.facade_bands)
                if not free[0]:
                    tv[k.FOE_X] = self._held_x
                if held is not None:
                    tv[k.FOE_Y], tv[k.ROAD] = held
                okv, inlv, _ = run(tv, self._om.copy(), free)
                ok = not okv or inl >= inlv
                if not ok and self._pitch_called(found):
                    # the votes run off under pitch: a pitching fit may explain more than theirs
                    tp = k.initial_theta(th[k.FOE_X], th[k.FOE_Y], p.facade_bands)
                    op = om.copy()
                    op[:, PITCHING] = 0.0
                    okp, inlp, totp = run(tp, op, np.array([True, True, False, False]))
                    if okp and inlp > inlv:
                        th, om, inl, tot, ok = tp, op, inlp, totp, True
                        self._mode, self._moved = PITCHING, T
                if ok:
                    self._won = T
        elif ok:
            ok = not far
        if not far:
            self._won = -math.inf
        if ok:
            self._th, self._om = th, om
            self._counts["fits"] += 1
            if held is None:
                self._remember_road(T, th[k.FOE_Y], th[k.ROAD])
            if not warm:
                self._warm_since = T
            if self._imu:
                self._update_gyro_turn(T, th[k.FOE_X])
            elif self._rotation:
                self._update_mode(T, th[k.FOE_X], found,
                                  lambda: self._turn_explains(run, th, om, inl),
                                  lambda: self._pitch_start(run, th, om, inl))
            if self._rotation:  # rotation 2: measured by the gyro, 1: fitted to the flow
                return (th[k.FOE_X], th[k.FOE_Y], inl, tot, *np.degrees(om[0] / self._prm.f),
                        2 if self._imu else 1)
            return (th[k.FOE_X], th[k.FOE_Y], inl, tot, 0.0, 0.0, 0.0, 0)
        self._th[:] = np.nan
        self._won = -math.inf
        self._road_held = None
        self._counts["votes"] += 1
        return (vx, vy, inl, tot, 0.0, 0.0, 0.0, 0)

    def _remember_road(self, T: int, y: float, a0: float) -> None:
        """Record a fit's FOE row and road scale, over the last ``heading_memory_s``."""
        self._road.append((T, y, a0))
        while self._road[0][0] < T - int(self.params.heading_memory_s * 1e6):
            self._road.popleft()

    def _held_road(self, th: np.ndarray) -> tuple[float, float] | None:
        """(FOE row, road scale) to hold the fit ``th`` at, or None when it is not running away:
        the road's scale ``a0 = V / (f h)`` changes only with the car's speed, so a fit whose
        scale fell below ``min_road_scale_ratio`` times the median of the recent fits (the last
        ``heading_memory_s`` of fits not held) while its FOE row rose above theirs fits an
        approaching obstacle's rows (a fronto-parallel surface, constant inverse time to
        contact) as road: the row and the scale are held at those medians, and stay held while
        the free fit's row stays above the held one."""
        from evchain.kernels import foe_fit as k

        if self._road_held is not None:  # held while the free fit's row stays above it
            if th[k.FOE_Y] < self._road_held[0]:
                return self._road_held
            self._road_held = None
            return None
        memory = self.params.heading_memory_s * 1e6
        if not self._road or self._road[-1][0] - self._road[0][0] < 0.9 * memory:
            return None
        a0 = _median([r[2] for r in self._road])
        if not th[k.ROAD] < self.params.min_road_scale_ratio * a0:  # the row's median unneeded
            return None
        y = _median([r[1] for r in self._road])
        if th[k.FOE_Y] < y:
            self._road_held = (y, a0)
        return self._road_held

    def flush(self):
        c = self._counts
        self.context.metrics[self.metrics_key("foe_fit")] = {
            "fit_times": c["fit times"], "fits_kept": c["fits"], "voting_estimates": c["votes"],
            "no_estimate": {"no recent voting estimate": c["no voting estimate"]}}
        if self.params.rotation_source == "imu":
            self.context.metrics[self.metrics_key("foe_fit")]["slabs_without_gyro"] = (
                c["slabs without gyro"])
        return None

    def _turn_explains(self, run, th, om, inl) -> bool:
        """Whether the yaw explains flow that a sideways shift of the FOE does not: the decayed
        inlier weight of the turning fit (the FOE's column held, yaw free) exceeds that of the
        level fit (the column free, no yaw) by more than ``turn_gain`` to enter the turning
        mode, at all to stay in it. ``run`` fits with the given free axes; ``th, om, inl``:
        the fit of the current mode at this time. From the
        level mode the turning fit starts from scratch at the column it would hold (a warm
        start would leave the slabs that already turn as outliers at yaw 0) and, if it wins,
        the fits go on from it. While turning the level fit is kept alongside, each from its
        own last one, and replaces the turning fit when the yaw does not explain enough."""
        from evchain.kernels import foe_fit as k

        more = 1.0 + self.params.turn_gain
        if self._mode != TURNING:
            self._level_fit = (th.copy(), om.copy())
            tt = k.initial_theta(float(np.median([c for _, c in self._level_x])), th[k.FOE_Y],
                                 self.params.facade_bands)
            ot = om.copy()
            ok, inl_turn, _ = run(tt, ot, np.array([False, False, True, False]))
            if ok and inl_turn > more * inl:
                self._th, self._om = tt, ot
                return True
            return False
        tl = (self._level_fit[0] if self._level_fit is not None else th).copy()
        ol = om.copy()  # the slabs of this fit time, the held pitch included
        ol[:, TURNING] = 0.0
        ok, inl_level, _ = run(tl, ol, np.array([True, False, False, False]))
        if not ok:  # no level fit to compare with: the turn stands
            self._level_fit = None
            return True
        self._level_fit = (tl, ol)
        return inl > inl_level

    def _pitch_called(self, probe: np.ndarray) -> bool:
        """Whether the level mode's probes call for pitch as for entering the pitching mode: the
        median of the last five (``probe`` the newest) turns faster than the threshold, and
        their mean over ``heading_memory_s`` does not (:meth:`_update_mode`)."""
        if self._mode != LEVEL or not self._rotation:
            return False
        latest = [*list(self._probes)[-4:], probe]
        lasting = np.array([w for _, w in self._pitch_probes] + [float(probe[PITCHING])])
        return (abs(_median([q[PITCHING] for q in latest])) > self._turn_pxs
                and not self._one_way(lasting))

    def _one_way(self, pitch: np.ndarray) -> bool:
        """Whether the probed pitch rates ``pitch`` (over ``heading_memory_s``) turn one way on
        average faster than the threshold: a ground plane's FOE row off, not the body's pitch."""
        # np.mean's own sum (pairwise) and division, without its wrapper
        return abs(float(np.add.reduce(pitch)) / len(pitch)) >= self._turn_pxs

    def _pitch_start(self, run, th, om, inl) -> None:
        """Entering the pitching mode: the fits go on from a pitching fit started from scratch
        at the level fit's FOE (scales unknown, every slab's pitch 0) if it explains more of the
        flow than the level fit (``th, om, inl``): a cold start finds every slab's pitch
        robustly, where a warm fit leaves the slabs that already pitch as outliers at pitch 0
        and refits only the newest."""
        from evchain.kernels import foe_fit as k

        tp = k.initial_theta(th[k.FOE_X], th[k.FOE_Y], self.params.facade_bands)
        op = om.copy()
        op[:, PITCHING] = 0.0
        ok, inl_p, _ = run(tp, op, np.array([True, True, False, False]))
        if ok and inl_p > inl:
            self._th, self._om = tp, op

    def _update_mode(self, T: int, x: float, probe: np.ndarray, turn_explains,
                     pitch_start) -> None:
        """Record the fit (its FOE column while not turning, its probed rotation) and switch
        mode. Only once the fits have run warm for 3 tau (a cold start's FOE is still on its
        way, and its probes see rotation where there is none): to turning (yaw free) or
        pitching (pitch free) when the median of the last probes turns about that axis faster
        than the threshold (turning first, and only with a full memory of settled level FOE
        columns to hold and while ``turn_explains()``; pitching's first fit from scratch,
        ``pitch_start()``), back to level once the mode's axis stayed below the threshold for 3
        tau, or at once when turning no longer explains more of the flow than the level fit
        kept alongside (:meth:`_turn_explains`)."""
        p = self.params
        memory = int(p.heading_memory_s * 1e6)
        window = 3 * p.tau_ms * 1000.0
        settled = T - self._warm_since >= window
        if self._mode != TURNING and settled:
            self._remember_column(T, x)
        self._probes.append(probe)
        rate = [abs(_median([q[a] for q in self._probes])) for a in range(2)]
        self._pitch_probes.append((T, float(probe[PITCHING])))
        while self._pitch_probes[0][0] < T - memory:
            self._pitch_probes.popleft()
        one_way = self._one_way(np.array([w for _, w in self._pitch_probes]))
        if self._mode == PITCHING and one_way:  # not the body's pitch (see the class doc)
            self._mode = LEVEL
        if self._mode != LEVEL and rate[self._mode] >= self._turn_pxs:
            self._moved = T
        if self._mode == TURNING and not turn_explains():  # a column shift does as well
            self._th, self._om = self._level_fit
            self._mode, self._held_x, self._level_fit = LEVEL, math.nan, None
            self._level_x.clear()  # the column of a settled level fit is yet to come
            return
        if not settled:
            return
        if (self._mode != TURNING and rate[TURNING] > self._turn_pxs
                and self._column_memory_full(T) and turn_explains()):
            self._hold_column(T)
        elif self._mode == LEVEL and rate[PITCHING] > self._turn_pxs and not one_way:
            self._mode, self._moved = PITCHING, T
            pitch_start()
        elif self._mode != LEVEL and T - self._moved >= window:
            if self._mode == TURNING:
                self._level_x.clear()
            self._mode, self._held_x, self._level_fit = LEVEL, math.nan, None

    def _update_gyro_turn(self, T: int, x: float) -> None:
        """rotation_source imu: record the fit's FOE column while not turning, and hold the
        column while the gyro turns about the yaw axis faster than the threshold, as with the
        flow's rotation (under a fast yaw the flow's errors, a share of its speed, pass for
        shifts of the column): at the median of the settled fits' columns over the last
        ``heading_memory_s``, entered once the fits have run warm for 3 tau with a full memory,
        left 3 tau after the yaw fell below the threshold."""
        window = 3 * self.params.tau_ms * 1000.0
        settled = T - self._warm_since >= window
        turns = abs(self._om[0, TURNING]) > self._turn_pxs
        if self._mode == TURNING:
            if turns:
                self._moved = T
            elif T - self._moved >= window:
                self._mode, self._held_x = LEVEL, math.nan
                self._level_x.clear()
            return
        if settled:
            self._remember_column(T, x)
        if turns and settled and self._column_memory_full(T):
            self._hold_column(T)

    def _remember_column(self, T: int, x: float) -> None:
        """Record a settled fit's FOE column, over the last ``heading_memory_s``."""
        self._level_x.append((T, x))
        while self._level_x[0][0] < T - int(self.params.heading_memory_s * 1e6):
            self._level_x.popleft()

    def _column_memory_full(self, T: int) -> bool:
        """Whether the recorded columns span (nearly) ``heading_memory_s`` up to T."""
        return bool(self._level_x) and (
            T - self._level_x[0][0] >= 0.9 * int(self.params.heading_memory_s * 1e6))

    def _hold_column(self, T: int) -> None:
        """Enter the turning mode at T with the FOE's column held at the recorded median."""
        self._mode, self._moved = TURNING, T
        self._held_x = float(np.median([c for _, c in self._level_x]))

    def _shift_slabs(self, T: int) -> int:
        """Move the slabs' rotations to fit time T: each slab's by the whole slabs since the
        last fit; new slabs start with the latest rotation, 0 on the axes the mode holds.
        Returns how many slabs are new (all of them at the first fit)."""
        if self._om_t is not None:
            m = (T - self._om_t) // self.params.estimate_every_us
            latest = self._om[0] * self._free()[1:]
            if m >= len(self._om):
                self._om[:] = latest
            elif m > 0:
                self._om[m:] = self._om[:-m].copy()
                self._om[:m] = latest
            self._om_t += m * self.params.estimate_every_us
            return min(int(m), len(self._om))
        self._om_t = T
        return len(self._om)

    def _gyro_slabs(self, T: int, n: int) -> None:
        """The newest ``n`` slabs' rotations (Om = f w, px/s) from the gyro: its mean rate
        over each slab (at :data:`GYRO_POINTS` evenly spread times, linear between samples:
        the model's rotation is constant within a slab, and the mean averages the gyro's noise
        down), less the bias; a slab the gyro does not cover (no samples around it) keeps 0
        and is counted."""
        P = self.params.estimate_every_us
        at = T - P * (np.arange(n)[:, None] + (np.arange(GYRO_POINTS) + 0.5) / GYRO_POINTS)
        w, covered = self._gyro.rate(at, np.asarray(self.params.gyro_bias_dps, np.float64),
                                     np.ones(3))
        full = covered.all(axis=1)
        self._om[:n] = np.where(full[:, None], w.mean(axis=1) * self._prm.f, 0.0)
        self._counts["slabs without gyro"] += int(n - full.sum())
