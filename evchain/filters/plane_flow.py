"""``plane_flow``: normal optical flow from local plane fits on the surface of active events."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from evchain.core.camera_scale import check_window_order, derived, derived_us, px_scale
from evchain.core.edge_arrival import EdgeArrivals
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, FlowPacket, Geometry
from evchain.core.series import DENSITY_BIN_US, FLOW_DENSITY, DensityCounter

DENSITY_SERIES = FLOW_DENSITY.name


class PlaneFlow(Filter):
    """Normal optical flow by local plane fitting (Benosman 2014, jAER's local planes).

    Per event: the surface of active events (latest timestamp per pixel and polarity) in the
    ``(2r+1)^2`` window around it, same polarity, at most ``window_us`` old, coordinates centred
    on the event, times in seconds. Variants: ``single`` (one least-squares fit of
    t = a x + b y + c), ``iterative`` (drop points farther than ``th2_s`` from the plane, refit
    until the parameters change < ``th1``), ``robust`` (homogeneous eigenvector fit, iterated),
    ``original`` (same, with the paper's biased per-component velocity -c/a, -c/b),
    ``savitzky_golay`` (mean pairwise slopes along rows and columns). Velocity v = g / |g|^2 with
    g = (dt/dx, dt/dy); flow faster than ``max_speed_pxs`` is dropped (jAER's th3). Every event
    updates the surface; events within ``refractory_us`` of the previous one at their pixel and
    polarity, and events within ``border_px`` of the border, get no flow. With ``centre_check``
    (default) an estimate is dropped when the event itself is more than ``th2_s`` off the
    fitted plane (the plane then describes older structure: the main source of flow pointing
    the wrong way on the reference scene). With ``max_window_us`` > ``window_us`` the window
    adapts to slow edges: a fit whose edge moved less than ``slow_px`` within the window (or,
    with ``refit_failed``, no fit) is redone with the window in which it moves ``slow_px``,
    up to ``max_window_us``, the centre check's limit scaled with the window. With
    ``min_window_us`` a fit whose edge moved more than ``fast_px`` within the window is redone
    with the shorter window in which it moves ``fast_px`` (at least ``min_window_us``), so that
    older edges that crossed the neighbourhood leave the fit. Degenerate fits
    (collinear or too few points, flat surfaces) are skipped, never NaN. Appends the series
    ``flow_density`` (t, n_in, n_out per 100 ms bin). Reports ``metrics.plane_flow``: the
    events, the flow events and, for the rest, why they got none (``no_flow``: refractory,
    border, too few neighbours, too narrow, no plane, centre check, too fast; the last fit's
    reason where the window adapted). Times and speeds left null follow the
    camera (their reference camera values scaled by ``camera_scale``: an image speed in px/s
    grows with the focal length, so the time in which an edge crosses so many pixels
    shrinks); lengths on the pixel grid do not.
    """

    name = "plane_flow"
    consumes = EventPacket
    produces = FlowPacket
    adds_series = (FLOW_DENSITY,)

    class Params(FilterParams):
        variant: Literal["single", "iterative", "robust", "original", "savitzky_golay"] = Field(
            "savitzky_golay", description="fit method (see the filter's description)")
        search_distance: int = Field(2, ge=1, le=7,
                                     description="r: neighbourhood (2r+1)^2 px [searchDistance]; "
                                                 "pixels of the grid, not derived")
        window_us: int | None = Field(
            None, gt=0, description="max age of neighbours [maxDtThreshold], µs; the time an "
                                    "edge takes to cross so many px, so null: 80 ms x 380.6 px "
                                    "/ f (camera_scale.derived_us)")
        refractory_us: int = Field(
            350_000, ge=0, description="no flow within this of the previous event at the pixel "
                                       "and polarity [refractoryPeriodUs], µs; longer than the "
                                       "bursts of slow edges near the FOE (chosen on the "
                                       "reference drive: the FOE error is flat from 300 to 400 "
                                       "ms; jAER and the thesis: 150 ms with surface updates). "
                                       "Not derived: a burst lasts while a smooth ramp of the "
                                       "scene crosses the pixel, an angle over an angular speed")
        border_px: int | None = Field(None, ge=0,
                                      description="no flow this close to the border; "
                                                  "default search_distance")
        min_points: int = Field(3, ge=3, description="fewest neighbours (incl. the event)")
        th1: float = Field(1e-5, gt=0, description="iterative fits: stop when the parameters "
                                                   "change less (s/px, or unit normal)")
        th2_s: float | None = Field(
            None, gt=0, description="iterative fits: drop points farther from the plane (s); "
                                    "centre_check limit. A time residual is a px residual over "
                                    "the speed, so null: 4 ms x 380.6 px / f")
        max_speed_pxs: float | None = Field(
            None, gt=0, le=1e12, description="th3 as a speed ceiling: drop faster flow, px/s; "
                                             "null: 1000 px/s x f / 380.6 px")
        max_iterations: int = Field(10, ge=1, description="iterative fits: refits at most")
        centre_check: bool = Field(
            True, description="drop the estimate when the event itself is farther than th2_s "
                              "from the fitted plane (evchain; jAER: false)")
        min_spread_px: float = Field(
            0.0, ge=0, description="neighbours must spread at least this (std. dev., px of the "
                                   "grid) across their principal direction: rejects "
                                   "single-edge-line sets")
        refractory_updates: bool = Field(
            False, description="an event within refractory_us still updates the surface (jAER); "
                               "false: it is dropped (the surface keeps each burst's onset: "
                               "with updates slow edges near the FOE alias, a pixel firing "
                               "many times while a smooth ramp crosses it)")
        max_window_us: int | None = Field(
            None, ge=0, description="speed-adaptive window: refit slow edges with a window up "
                                    "to this long, µs (0: off; else longer than window_us; off "
                                    "for original). It sets the slowest edge resolved, slow_px "
                                    "/ max_window_us px/s, so null: 500 ms x 380.6 px / f "
                                    "(chosen on the reference drive)")
        slow_px: float = Field(
            2.0, gt=0, description="adaptive window: refit when the edge moved less than this "
                                   "(px of the grid, not derived) within the window, with the "
                                   "window in which it moves this far")
        refit_failed: bool = Field(
            True, description="adaptive window: also refit with max_window_us when the fit "
                              "with window_us gives no estimate")

        min_window_us: int = Field(
            0, ge=0, description="short window for fast edges (0: off; else shorter than "
                                 "window_us; needs no max_window_us): a first fit whose edge "
                                 "moved more than fast_px within window_us is redone with the "
                                 "window in which it moves fast_px, at least this, µs; the "
                                 "first fit stands when the shorter one fails; taken as given")
        fast_px: float = Field(3.0, gt=0, description="short window: the distance, px of the "
                                                      "grid")

        @model_validator(mode="after")
        def _adaptive_window(self):
            given = self.window_us is not None
            if given and self.max_window_us and self.max_window_us <= self.window_us:
                raise ValueError(f"max_window_us ({self.max_window_us}) must exceed window_us "
                                 f"({self.window_us}), or be 0 (off)")
            if given and self.min_window_us and self.min_window_us >= self.window_us:
                raise ValueError(f"min_window_us ({self.min_window_us}) must be shorter than "
                                 f"window_us ({self.window_us}), or be 0 (off)")
            if self.max_window_us and self.variant == "original":
                raise ValueError("max_window_us (speed-adaptive window) does not apply to "
                                 "variant original (it fits velocities, not a time plane)")
            if self.min_window_us and self.variant == "original":
                raise ValueError("min_window_us (short window) does not apply to variant "
                                 "original")
            return self

    def kernel_params(self, geometry: Geometry):
        """The kernel's parameters on this camera (null ones derived from it), checked."""
        from evchain.kernels.plane_flow import VARIANTS, PlaneParams
        from evchain.kernels.records import record

        q = self.params
        window = derived_us(q.window_us, 80_000, geometry)
        longest = (0 if q.variant == "original"
                   else derived_us(q.max_window_us, 500_000, geometry))
        check_window_order("plane_flow", window, longest, q.min_window_us, geometry)
        return record(
            PlaneParams, variant=VARIANTS[q.variant], r=q.search_distance,
            window_us=window, refractory_us=q.refractory_us,
            margin=q.search_distance if q.border_px is None else q.border_px,
            min_points=q.min_points, th1=q.th1,
            th2=q.th2_s if q.th2_s is not None else 0.004 / px_scale(geometry),
            max_speed=derived(q.max_speed_pxs, 1000.0, geometry),
            max_iter=q.max_iterations, min_spread=q.min_spread_px, centre_check=q.centre_check,
            max_window_us=longest, slow_px=q.slow_px, refit_failed=q.refit_failed,
            refractory_updates=q.refractory_updates, min_window_us=q.min_window_us,
            fast_px=q.fast_px)

    def reset(self) -> None:
        g = self.context.geometry
        self._state = self._arrivals = self._prm = None
        if g is not None:
            self._new_state(g)
        self._density = DensityCounter(DENSITY_BIN_US)
        self._end = None
        self._geometry = g
        from evchain.kernels.plane_flow import WHY_NO_FLOW

        self._why = np.zeros(len(WHY_NO_FLOW) + 1, np.int64)  # why no flow, then the flow

    def _new_state(self, g: Geometry) -> None:
        """The surface, the pixels' runs (``t_edge``) and the kernel's constants for ``g``."""
        from evchain.kernels.plane_flow import new_state

        self._state = new_state(g.width, g.height)
        self._arrivals = EdgeArrivals(g.height, g.width)
        self._prm = self.kernel_params(g)

    def process(self, packet: EventPacket) -> FlowPacket:
        from evchain.kernels.plane_flow import plane_flow_kernel

        g = packet.geometry
        if self._state is None or self._state.shape[1:] != (g.height, g.width):
            self._new_state(g)
        self._geometry = g
        n = len(packet)
        idx = np.empty(n, np.int64)
        vx = np.empty(n, np.float64)
        vy = np.empty(n, np.float64)
        k = 0
        if n:
            k = plane_flow_kernel(packet.x, packet.y, packet.t, packet.p, self._state,
                                  self._prm, idx, vx, vy, self._why)
        idx = idx[:k]
        out = FlowPacket.from_events(packet, idx, vx[:k], vy[:k], self._arrivals.of(packet))
        self._end = packet.t_end
        return out.with_series(DENSITY_SERIES, self._density.add(packet.t, packet.t[idx],
                                                                 packet.t_end))

    def flush(self) -> FlowPacket | None:
        from evchain.kernels.plane_flow import WHY_NO_FLOW

        counts = self._why.tolist()
        self.context.metrics[self.metrics_key("plane_flow")] = {
            "events": sum(counts), "flow_events": counts[-1],
            "no_flow": dict(zip(WHY_NO_FLOW, counts[:-1], strict=True))}
        if self._end is None:
            return None
        return FlowPacket.empty(self._geometry, self._end, self._end).with_series(
            DENSITY_SERIES, self._density.flush())
