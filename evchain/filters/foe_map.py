"""``foe_map``: focus of expansion by half-plane voting (Clady et al. 2014, thesis Algorithm 1)."""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket, Geometry, series_array
from evchain.errors import DataError

FOE_DTYPE = [("t", "i8"), ("x", "f8"), ("y", "f8"), ("support", "f8"), ("total", "f8")]


def region_rows(geometry: Geometry, radius_px: float | None):
    """Region A as rows: ``(x0, y0, lo, hi)`` with absolute column bounds per row (hi < lo: empty).

    A disc of ``radius_px`` around the principal point (cells whose centre lies inside), clipped
    to the sensor; the whole sensor when ``radius_px`` is None.
    """
    w, h = geometry.width, geometry.height
    if radius_px is None:
        lo = np.zeros(h, np.int64)
        hi = np.full(h, w - 1, np.int64)
        return 0, 0, lo, hi
    cx, cy, r = float(geometry.cx), float(geometry.cy), float(radius_px)
    y_first = max(0, math.ceil(cy - r))
    y_last = min(h - 1, math.floor(cy + r))
    if y_last < y_first:
        raise DataError(f"foe_map: region A (radius {r} px around ({cx}, {cy})) misses the "
                        f"{w}x{h} sensor; use a larger region_radius_px or none")
    ys = np.arange(y_first, y_last + 1)
    lo = np.empty(len(ys), np.int64)
    hi = np.empty(len(ys), np.int64)
    for i, yy in enumerate(ys):
        xs = np.arange(w)
        inside = (xs - cx) ** 2 + (yy - cy) ** 2 <= r * r
        if inside.any():
            lo[i], hi[i] = xs[inside][0], xs[inside][-1]
        else:
            lo[i], hi[i] = 0, -1
    x0 = int(lo[hi >= lo].min()) if (hi >= lo).any() else 0
    return x0, int(y_first), lo, hi


class FoeMap(Filter):
    """Focus of expansion by decaying half-plane votes of normal flow (Clady 2014), O(rows)/event.

    Each flow event v at p votes for the half-plane {q : (p - q).v > 0} inside region A (a disc
    around the principal point, or the whole sensor); votes decay with ``tau_ms``. Estimates are
    read at every multiple of ``estimate_every_us`` (from the events before that time, so packet
    cuts do not change them) and appended to series ``foe``: t, x, y (px, sub-pixel centroid of
    the near-maximal cells), support (decayed votes at the maximum), total (all decayed votes).
    The flow passes through unchanged.
    """

    name = "foe_map"
    consumes = FlowPacket
    produces = FlowPacket

    class Params(FilterParams):
        tau_ms: float = Field(100.0, gt=0, description="decay time constant of the votes")
        region_radius_px: float | None = Field(
            60.0, gt=0, description="radius of region A around the principal point; "
            "null = the whole sensor (slower: every event then touches every row)")
        estimate_every_us: int = Field(1000, ge=1, description="period of the FOE estimates")
        refine_fraction: float = Field(
            0.02, ge=0, lt=1, description="sub-pixel refinement: centroid of the cells within "
            "this fraction of (max - min) below the maximum, weighted by height; 0 = centroid "
            "of the maximal set only")
        min_speed_pxs: float = Field(0.0, ge=0, description="ignore flow slower than this")
        max_angle_deg: float | None = Field(
            None, gt=0, le=180, description="angular gating: ignore flow deviating more than "
            "this from the direction away from the current estimate (null = off)")
        min_support: float = Field(0.0, ge=0, description="emit an estimate only when the "
                                   "decayed votes at the maximum reach this")

    def reset(self) -> None:
        self._geometry: Geometry | None = None
        self._ist = np.zeros(4, np.int64)
        self._fst = np.zeros(5, np.float64)
        self._started = False

    def _allocate(self, geometry: Geometry) -> None:
        p = self.params
        self._geometry = geometry
        self._x0, self._y0, self._lo, self._hi = region_rows(geometry, p.region_radius_px)
        nx = int(self._hi.max()) - self._x0 + 2 if len(self._hi) else 1
        self._diff = np.zeros((len(self._lo), max(nx, 1)), np.float64)
        if p.region_radius_px is None:
            self._disc = ((geometry.width - 1) / 2.0, (geometry.height - 1) / 2.0,
                          0.5 * math.hypot(geometry.width, geometry.height))
        else:
            self._disc = (float(geometry.cx), float(geometry.cy), float(p.region_radius_px))

    def process(self, packet: FlowPacket) -> FlowPacket:
        if not isinstance(packet, FlowPacket):
            raise DataError(f"foe_map needs a FlowPacket, got {type(packet).__name__}")
        from evchain.kernels import foe_map as k

        p = self.params
        if self._geometry is None:
            self._allocate(packet.geometry)
        elif packet.geometry != self._geometry:
            raise DataError(f"foe_map: sensor geometry changed from {self._geometry} to "
                            f"{packet.geometry}")
        period = int(p.estimate_every_us)
        if not self._started:
            self._ist[1] = -(-packet.t_start // period) * period
            self._started = True
        n_max = max(0, -(-(packet.t_end - int(self._ist[1])) // period))
        out = np.zeros(n_max, dtype=FOE_DTYPE)
        cols = [np.empty(n_max, np.int64)] + [np.empty(n_max, np.float64) for _ in range(4)]
        tau_us = p.tau_ms * 1000.0
        gate_on = p.max_angle_deg is not None
        cos_gate = math.cos(math.radians(p.max_angle_deg)) if gate_on else -1.0
        n = k.process(packet.x, packet.y, packet.t, packet.vx, packet.vy, self._diff, self._lo,
                      self._hi, self._x0, self._y0, self._fst, self._ist, tau_us,
                      float(p.min_speed_pxs), cos_gate, gate_on, period,
                      float(p.refine_fraction), float(p.min_support), int(packet.t_end),
                      *self._disc, *cols)
        for name, col in zip(("t", "x", "y", "support", "total"), cols, strict=True):
            out[name] = col
        return packet.with_series("foe", out[:n])

    def map_now(self, t_us: int) -> np.ndarray:
        """The dense vote map decayed to ``t_us`` (NaN outside region A), for tests and plots.

        Rows are image rows ``y0..``, columns image columns ``x0..``; see :attr:`origin`.
        """
        from evchain.kernels import foe_map as k

        out = np.empty((self._diff.shape[0], self._diff.shape[1] - 1), np.float64)
        k.materialize(self._diff, self._lo, self._hi, self._x0, self._y0, self._fst[0], out)
        return out * math.exp(-(t_us - int(self._ist[0])) / (self.params.tau_ms * 1000.0))

    @property
    def origin(self) -> tuple[int, int]:
        return self._x0, self._y0


def foe_series(entries_x, entries_y, t, support, total=None) -> np.ndarray:
    """Build a ``foe`` series array (helper for tests and other producers)."""
    total = support if total is None else total
    return series_array(FOE_DTYPE, t=t, x=entries_x, y=entries_y, support=support, total=total)
