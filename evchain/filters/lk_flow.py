"""Filter ``lk_flow``: event-based Lucas-Kanade optical flow (Benosman 2012, after jAER)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from evchain.core.camera_scale import check_window_order, derived, derived_us
from evchain.core.edge_arrival import EdgeArrivals
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, FlowPacket, Geometry
from evchain.core.series import DENSITY_BIN_US, FLOW_DENSITY, DensityCounter
from evchain.errors import FilterError

DENSITY_SERIES = FLOW_DENSITY.name

GRADIENTS = {"backward": 0, "central": 1, "central2": 2, "savitzky_golay": 3}


class LKFlow(Filter):
    """Lucas-Kanade normal flow from per-pixel event counts (jAER-faithful or calibrated px/s).

    Per pixel and polarity a FIFO of recent timestamps; the flow of an event is the least-squares
    solution of the brightness-constancy equations over its (2r+1)² neighbourhood, with the
    structure tensor's eigenvalues choosing full flow, normal flow or none. ``mode: faithful``
    reproduces jAER's LucasKanadeFlow (speeds not physically scaled: count x 20 heuristic);
    ``mode: calibrated`` (default) replaces the count image by each active pixel's onset time
    scaled to the window, whose time derivative is known exactly, which gives px/s. Calibrated
    mode can adapt the window to the edge's speed: longer for slow edges (``max_window_us``),
    and a short first window for fast ones (``min_window_us``). Emits only
    events with non-zero flow, and appends the series ``flow_density`` (t, n_in, n_out per 100 ms
    bin) for the scorer. Times and speeds left null follow the camera (their reference camera
    values scaled by ``camera_scale``: an image speed in px/s grows with the focal length, so
    the time in which an edge crosses so many pixels shrinks); lengths on the pixel grid do
    not. See docs/explanation/lk_flow.md.
    """

    name = "lk_flow"
    consumes = EventPacket
    produces = FlowPacket
    adds_series = (FLOW_DENSITY,)

    class Params(FilterParams):
        search_distance: int = Field(2, ge=1, le=8, description=(
            "half-width r of the (2r+1)² neighbourhood [jAER searchDistance]; pixels of the "
            "sensor's grid (the stencil of the gradient), not derived"))
        window_us: int | None = Field(None, ge=1, le=100_000_000, description=(
            "age of the events counted in the neighbourhood, µs [jAER maxDtThreshold]; the "
            "time an edge takes to cross so many px, so null: 80 ms x 380.6 px / f (80 ms on "
            "the reference camera, camera_scale.derived_us)"))
        refractory_us: int | None = Field(None, ge=0, le=100_000_000, description=(
            "no flow for an event that follows the previous one at its pixel and polarity by "
            "less than this, µs; its timestamp still enters the memory [refractoryPeriodUs]; "
            "the time an edge takes to cross a pixel, so null: 150 ms x 380.6 px / f (the "
            "thesis's selection on the reference camera, Table 4.3)"))
        eig_threshold: float = Field(1.0, ge=0.0, description=(
            "faithful mode: confidence threshold th on the structure tensor's eigenvalues "
            "(lambda1 < th: none, lambda2 < th: normal flow, else full) [jAER thr]"))
        eig_ratio: float = Field(0.1, ge=0.0, le=1.0, description=(
            "calibrated mode: full flow only when lambda2 >= eig_ratio * lambda1 (scale-free), "
            "else normal flow along the dominant eigenvector"))
        gradient: Literal["backward", "central", "central2", "savitzky_golay"] = Field(
            "savitzky_golay", description=(
                "spatial derivative: backward, central first order, central second order "
                "(5 points) or one Savitzky-Golay plane fit of the neighbourhood"))
        speed_control: bool = Field(True, description=(
            "drop events faster than max_speed_factor x the running mean speed"))
        speed_control_mix: float = Field(1e-3, gt=0.0, le=1.0, description=(
            "mixing factor of the running mean speed [jAER speedMixingFactor]"))
        max_speed_factor: float = Field(2.0, gt=0.0, description=(
            "speed control rejects speeds above this factor x the mean "
            "[jAER excessSpeedRejectFactor]"))
        max_speed_pxs: float | None = Field(None, gt=0.0, description=(
            "calibrated mode: drop flow faster than this, px/s; null: 1e5 px/s x f / 380.6 px"))
        refit_tolerance: float = Field(0.25, ge=0.0, description=(
            "calibrated mode: drop equations that disagree with the first solution (finite "
            "differences: relative slope mismatch above this; Savitzky-Golay: pixels farther "
            "than this, px of the grid, from the plane) and solve again once; 0 = off"))
        centre_check_px: float = Field(0.5, ge=0.0, description=(
            "calibrated mode: drop the estimate when the event's own onset lies farther than "
            "this (px of the grid, along the normal) from the plane the flow implies through "
            "its active neighbours, i.e. the neighbours belong to an older edge; 0 = off"))
        mode: Literal["faithful", "calibrated"] = Field("calibrated", description=(
            "faithful: jAER's numbers (uncalibrated magnitudes); calibrated: px/s"))
        fifo_depth: int = Field(8, ge=1, le=256, description=(
            "timestamps kept per pixel and polarity; must exceed the events a pixel fires "
            "within window_us (max_window_us when set), or counts saturate"))
        max_window_us: int | None = Field(None, ge=0, le=100_000_000, description=(
            "calibrated mode: speed-adaptive window, off at 0. An event whose estimate with "
            "window_us fails or says the edge crosses fewer than slow_px px within the window "
            "is estimated again with min(max_window_us, slow_px / speed) (max_window_us after a "
            "failure; at most 3 estimates); a longer window's estimate is kept only if the edge "
            "is slow enough to need it, µs. It sets the slowest edge resolved, slow_px / "
            "max_window_us px/s, so null: 600 ms x 380.6 px / f (5 px/s on the reference "
            "camera: a far obstacle's edges 15 px from the FOE at 3 s to contact; chosen on "
            "the tuning set); off in faithful mode"))
        slow_px: float = Field(3.0, gt=0.0, le=100.0, description=(
            "calibrated mode with max_window_us: the distance, px of the grid, an edge must "
            "cross within its window to be resolved (3 exceeds the ~2 events a pixel fires "
            "while an edge passes, so the onset of the pixel behind lies inside the window); "
            "not derived"))

        min_window_us: int = Field(0, ge=0, le=100_000_000, description=(
            "calibrated mode: two time scales, off at 0 (else shorter than window_us). Each "
            "event is first estimated with min_window_us; that estimate stands when the edge "
            "crosses at least fast_px px within it, else the event is estimated as without it "
            "(window_us, then the speed-adaptive window), µs; taken as given"))
        fast_px: float = Field(8.0, gt=0.0, le=100.0, description=(
            "calibrated mode with min_window_us: the distance, px of the grid, an edge must "
            "cross within min_window_us for the short window's estimate to stand"))

        @model_validator(mode="after")
        def _adaptive_window(self):
            given = self.window_us is not None
            if given and self.max_window_us and self.max_window_us <= self.window_us:
                raise ValueError(f"max_window_us ({self.max_window_us}) must exceed window_us "
                                 f"({self.window_us}), or be 0 (off)")
            if given and self.min_window_us and self.min_window_us >= self.window_us:
                raise ValueError(f"min_window_us ({self.min_window_us}) must be shorter than "
                                 f"window_us ({self.window_us}), or be 0 (off)")
            if self.max_window_us and self.mode == "faithful":
                raise ValueError("max_window_us (speed-adaptive window) is calibrated mode "
                                 "only")
            if self.min_window_us and self.mode == "faithful":
                raise ValueError("min_window_us (short window) is calibrated mode only")
            return self

    def kernel_params(self, geometry: Geometry):
        """The kernel's parameters on this camera (null ones derived from it), checked."""
        from evchain.kernels.lk_flow import LKParams
        from evchain.kernels.records import record

        q = self.params
        window = derived_us(q.window_us, 80_000, geometry)
        longest = 0 if q.mode == "faithful" else derived_us(q.max_window_us, 600_000, geometry)
        check_window_order("lk_flow", window, longest, q.min_window_us, geometry)
        return record(
            LKParams, r=q.search_distance, window_us=window,
            refractory_us=derived_us(q.refractory_us, 150_000, geometry),
            gradient=GRADIENTS[q.gradient], faithful=q.mode == "faithful",
            eig_threshold=q.eig_threshold, eig_ratio=q.eig_ratio, speed_control=q.speed_control,
            mix=q.speed_control_mix, max_factor=q.max_speed_factor,
            max_speed_pxs=derived(q.max_speed_pxs, 1e5, geometry),
            refit_tolerance=q.refit_tolerance, centre_check_px=q.centre_check_px,
            max_window_us=longest, slow_px=q.slow_px, min_window_us=q.min_window_us,
            fast_px=q.fast_px)

    def reset(self) -> None:
        self._density = DensityCounter(DENSITY_BIN_US)
        self._last = None
        g = self.context.geometry
        self._state = None
        self._shape = None
        self._prm = None
        if g is not None:
            self._prm = self.kernel_params(g)
            self._new_state(g)

    def _new_state(self, g: Geometry) -> None:
        """The kernel's per-pixel state and the pixels' runs (``t_edge``) for sensor ``g``."""
        from evchain.kernels.lk_flow import new_state

        self._state = new_state(g.height, g.width, self.params.fifo_depth)
        self._shape = (g.height, g.width)
        self._arrivals = EdgeArrivals(g.height, g.width)

    def process(self, packet: EventPacket) -> FlowPacket:
        from evchain.kernels.lk_flow import lk_flow_run

        g = packet.geometry
        if self._prm is None:
            self._prm = self.kernel_params(g)
        if self._state is None or self._shape != (g.height, g.width):
            if self._state is not None:
                raise FilterError(f"lk_flow: sensor changed from {self._shape[1]}x"
                                  f"{self._shape[0]} to {g.width}x{g.height} mid-stream")
            self._new_state(g)
        n = len(packet)
        idx = np.empty(n, np.int64)
        vx = np.empty(n, np.float64)
        vy = np.empty(n, np.float64)
        if n:
            n_out = lk_flow_run(packet.x, packet.y, packet.t, packet.p, self._state, self._prm,
                                idx, vx, vy)
        else:
            n_out = 0
        idx = idx[:n_out]
        out = FlowPacket.from_events(packet, idx, vx[:n_out], vy[:n_out],
                                     self._arrivals.of(packet))
        self._last = packet
        return out.with_series(DENSITY_SERIES, self._density.add(packet.t, packet.t[idx],
                                                                 packet.t_end))

    def flush(self) -> FlowPacket | None:
        if self._last is None:
            return None
        end = self._last.t_end
        return FlowPacket.empty(self._last.geometry, end, end).with_series(
            DENSITY_SERIES, self._density.flush())
