"""``foe_map``: focus of expansion by half-plane voting (Clady et al. 2014, thesis Algorithm 1)."""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from evchain.core.camera_scale import derived
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.series import FOE
from evchain.errors import DataError


def region_cells(geometry: Geometry, radius_px: float | None):
    """Region A: ``(x0, y0, lo, hi, clo, chi)``: its bounding box origin, the absolute column
    bounds per row ``y0..`` and the absolute row bounds per column ``x0..`` (hi < lo: empty).

    A disc of ``radius_px`` around the principal point (cells whose centre lies inside), clipped
    to the sensor; the whole sensor when ``radius_px`` is None. Both are convex, so every row and
    column of A is one interval.
    """
    w, h = geometry.width, geometry.height
    ys, xs = np.mgrid[0:h, 0:w]
    if radius_px is None:
        mask = np.ones((h, w), bool)
    else:
        r = float(radius_px)
        mask = (xs - float(geometry.cx)) ** 2 + (ys - float(geometry.cy)) ** 2 <= r * r
        if not mask.any():
            raise DataError(f"foe_map: region A (radius {r} px around ({geometry.cx}, "
                            f"{geometry.cy})) holds no pixel of the {w}x{h} sensor; use a "
                            "larger region_radius_px or 0 (the whole sensor)")
    rows = np.nonzero(mask.any(axis=1))[0]
    cols = np.nonzero(mask.any(axis=0))[0]
    y0, x0 = int(rows[0]), int(cols[0])
    box = mask[y0:rows[-1] + 1, x0:cols[-1] + 1]

    def bounds(m, offset):
        any_ = m.any(axis=1)
        first = np.where(any_, np.argmax(m, axis=1), 0) + offset
        last = np.where(any_, m.shape[1] - 1 - np.argmax(m[:, ::-1], axis=1), -1) + offset
        last = np.where(any_, last, first - 1)
        return first.astype(np.int64), last.astype(np.int64)

    lo, hi = bounds(box, x0)
    clo, chi = bounds(box.T, y0)
    return x0, y0, lo, hi, clo, chi


def cell_geometry(geometry: Geometry, cell_px: int, radius_px: float | None):
    """The sensor in map cells of ``cell_px`` pixels (cell c covers pixels ``cell_px * c ..``,
    its centre is pixel ``cell_px * c + (cell_px - 1) / 2``) and region A's radius in cells."""
    if cell_px == 1:
        return geometry, radius_px
    g = Geometry(-(-geometry.width // cell_px), -(-geometry.height // cell_px),
                 cx=float(to_cells(geometry.cx, cell_px)),
                 cy=float(to_cells(geometry.cy, cell_px)))
    return g, None if radius_px is None else radius_px / cell_px


def to_cells(v, cell_px: int):
    """Pixel coordinates -> cell coordinates (float64; cell centres are integers)."""
    return (np.asarray(v, np.float64) - 0.5 * (cell_px - 1)) / cell_px


def from_cells(v, cell_px: int):
    """Cell coordinates -> pixel coordinates."""
    return np.asarray(v, np.float64) * cell_px + 0.5 * (cell_px - 1)


class FoeMap(Filter):
    """Focus of expansion by decaying half-plane votes of normal flow (Clady 2014), O(rows)/event.

    Each flow event v at p votes for the half-plane {q : (p - q).v > 0} inside region A (a disc
    around the principal point, or the whole sensor); votes decay with ``tau_ms``. Estimates are
    read at every multiple of ``estimate_every_us`` (from the events before that time, so packet
    cuts do not change them) and appended to series ``foe``: t, x, y (px, sub-pixel centroid of
    the near-maximal cells), support (decayed votes at the maximum), total (all decayed votes).
    The flow passes through unchanged.

    No estimate is emitted before the first vote, nor while the votes do not agree more than
    flow without any FOE would: if flow directions were independent of positions (sensor
    noise, a uniform scene with noise), every cell would lie in each vote's half-plane with
    probability 1/2, so the consensus ``support / total`` of the best of the M cells of A
    exceeds ``1/2 + sqrt(ln(M / significance) / (2 n))`` with probability at most
    ``significance`` (Hoeffding's inequality for the weighted votes, a union bound over the
    cells; n = (sum w)^2 / sum w^2, the effective number of votes). Few votes (n small) give no
    estimate either. ``metrics.foe_map`` counts the reads, the estimates and the reads without
    one, by reason.
    """

    name = "foe_map"
    consumes = FlowPacket
    produces = FlowPacket
    adds_series = (FOE,)

    class Params(FilterParams):
        tau_ms: float = Field(100.0, gt=0, description="decay time constant of the votes")
        region_radius_px: float | None = Field(
            None, ge=0, description="radius of region A around the principal point, px (an "
            "angle: scales with the camera); null: 60 px x f / 380.6 px (9 deg of view; 60 px "
            "on the reference camera, camera_scale.px_scale); 0 = the whole sensor (slower: "
            "every event then touches every row)")
        estimate_every_us: int = Field(
            10_000, ge=1, description="period of the FOE estimates; the default is foe_fit's "
            "and ttc's period (they read the latest estimate at their own times only)")
        refine_fraction: float = Field(
            0.05, ge=0, lt=1, description="sub-pixel refinement: centroid of the cells within "
            "this fraction of (max - min) below the maximum, weighted by height; 0 = centroid "
            "of the maximal set only")
        min_speed_pxs: float = Field(0.0, ge=0, description="ignore flow slower than this, "
                                     "px/s of this camera (0 = none: not derived)")
        max_angle_deg: float | None = Field(
            None, gt=0, le=180, description="angular gating: ignore flow deviating more than "
            "this from the direction away from the current estimate (null = off)")
        min_support: float = Field(0.0, ge=0, description="emit an estimate only when the "
                                   "decayed votes at the maximum reach this")
        speed_weight_pxs: float | None = Field(
            None, ge=0, description="weigh each vote by s0 / (s0 + speed) with this s0, px/s: "
            "slow normal flow (a boundary line close to the FOE, a tight constraint) counts "
            "more than fast flow; an angular speed, so null: 5 px/s x f / 380.6 px; 0 = every "
            "vote weighs 1")
        cell_px: int = Field(1, ge=1, le=16, description="map resolution: square cells of this "
                             "many pixels (the votes are tested at the cell centres); 2 halves "
                             "the per-event work and quarters the reads. Sensor pixels, not "
                             "derived: a choice of precision against cost")
        significance: float | None = Field(
            1e-3, gt=0, lt=1, description="emit an estimate only when its consensus (support / "
            "total) exceeds what flow without an FOE (directions independent of positions) "
            "reaches with at most this probability at a read: 1/2 + sqrt(ln(M / significance) "
            "/ (2 n)), M the cells of A, n the effective number of votes; null: off")

    def reset(self) -> None:
        self._geometry: Geometry | None = None
        self._state = None
        self._started = False
        self._reads = 0       # reads due (the noise-level ones are counted by the kernel)
        self._estimates = 0   # estimates emitted

    def _allocate(self, geometry: Geometry) -> None:
        from evchain.kernels import foe_map as k

        p = self.params
        self._geometry = geometry
        radius_px = derived(p.region_radius_px, 60.0, geometry) or None  # 0: the whole sensor
        cg, radius = cell_geometry(geometry, p.cell_px, radius_px)
        x0, y0, lo, hi, clo, chi = region_cells(cg, radius)
        self._x0, self._y0 = x0, y0
        self._state = k.new_state(lo, hi, clo, chi)
        self._state_arrays = tuple(self._state)  # numba types a plain tuple faster per call
        if radius is None:
            cx, cy, r = ((cg.width - 1) / 2.0, (cg.height - 1) / 2.0,
                         0.5 * math.hypot(cg.width, cg.height))
        else:
            cx, cy, r = float(cg.cx), float(cg.cy), float(radius)
        gate_on = p.max_angle_deg is not None
        self._prm = k.new_params(
            tau_us=p.tau_ms * 1000.0, min_speed_pxs=p.min_speed_pxs,
            cos_gate=math.cos(math.radians(p.max_angle_deg)) if gate_on else -1.0,
            gate_on=gate_on, period_us=p.estimate_every_us, refine_fraction=p.refine_fraction,
            min_support=p.min_support, speed_w0=derived(p.speed_weight_pxs, 5.0, geometry),
            cx=cx, cy=cy, radius=r, x0=x0, y0=y0, noise_test=p.significance is not None,
            log_m_alpha=self._log_m_alpha(lo, hi))
        self._period = int(p.estimate_every_us)
        self._cell = int(p.cell_px)
        self._next_read = self._state.carry["next_read"]  # a view: the kernel's next read
        self._kernel = k

    def process(self, packet: FlowPacket) -> FlowPacket:
        if not isinstance(packet, FlowPacket):
            raise DataError(f"foe_map needs a FlowPacket, got {type(packet).__name__}")
        if self._geometry is None:
            self._allocate(packet.geometry)
        elif packet.geometry is not self._geometry and packet.geometry != self._geometry:
            raise DataError(f"foe_map: sensor geometry changed from {self._geometry} to "
                            f"{packet.geometry}")
        k = self._kernel
        period = self._period
        if not self._started:
            k.start(self._state, -(-packet.t_start // period) * period)
            self._started = True
        n_max = max(0, -(-(packet.t_end - int(self._next_read[0])) // period))
        self._reads += n_max
        out = np.zeros(n_max, FOE.dtype)  # the kernel writes position and weights; no rotation
        cell = self._cell
        if cell == 1:
            x, y = packet.x, packet.y
        else:
            x, y = to_cells(packet.x, cell), to_cells(packet.y, cell)
        n = k.process(x, y, packet.t, packet.vx, packet.vy, self._state_arrays, self._prm,
                      int(packet.t_end), out)
        if n < n_max:
            out = out[:n]
        self._estimates += n
        if cell != 1:
            out["x"] = from_cells(out["x"], cell)
            out["y"] = from_cells(out["y"], cell)
        return packet.with_series("foe", out)

    def _log_m_alpha(self, lo: np.ndarray, hi: np.ndarray) -> float:
        """ln(M / significance), M = the cells of A (the union bound of the noise test); 0.0
        when the test is off."""
        if self.params.significance is None:
            return 0.0
        cells = int(np.maximum(hi - lo + 1, 0).sum())
        return math.log(cells / self.params.significance)

    def flush(self):
        noise = 0 if self._state is None else int(self._state.carry["noise_level"][0])
        self.context.metrics[self.metrics_key("foe_map")] = {
            "reads": self._reads, "estimates": self._estimates,
            "no_estimate": {"no votes yet": self._reads - self._estimates - noise,
                            "consensus at noise level": noise}}
        return None

    def map_now(self, t_us: int) -> np.ndarray:
        """The dense vote map decayed to ``t_us`` (NaN outside region A), for tests and plots.

        Rows are image rows ``y0..``, columns image columns ``x0..`` (cells of ``cell_px``
        pixels when that is not 1); see :attr:`origin`.
        """
        from evchain.kernels import foe_map as k

        return k.dense_map(self._state, self._x0, t_us, self.params.tau_ms * 1000.0)

    @property
    def origin(self) -> tuple[int, int]:
        """Cell (column, row) of the map's first entry (pixels when ``cell_px`` is 1)."""
        return self._x0, self._y0


def foe_series(entries_x, entries_y, t, support, total=None) -> np.ndarray:
    """Build a ``foe`` series array (helper for tests and other producers)."""
    total = support if total is None else total
    return FOE.array(t=t, x=entries_x, y=entries_y, support=support, total=total)
