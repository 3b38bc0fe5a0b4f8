"""``ttc``: time to contact from normal flow and the FOE, clustered per obstacle (thesis 3.3.2)."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.camera_scale import derived
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.series import FOE, ROTATION_FIELDS, TTC, TTC_CLUSTERS
from evchain.errors import DataError

TTC_DTYPE = TTC.dtype
#: the largest relative spread of a credible cluster's samples (see Ttc.Params.max_rel_spread)
MAX_REL_SPREAD = 1.0
CLUSTER_DTYPE = TTC_CLUSTERS.dtype


class Ttc(Filter):
    """Time to contact: tau = (p - foe).v / |v|^2 in region B, clustered, fused per cluster.

    Uses the latest estimate of the ``foe`` series (from ``foe_map`` upstream; nothing before
    the first one). Flow events below the FOE, within ``region_b_half_width_px`` of it
    horizontally, at least ``min_distance_px`` from it, diverging and of plausible speed give
    one tau each: with ``baseline_px`` > 0 from where the edge was earlier (the edge's arrival
    at each pixel, the flow packet's ``t_edge`` of the pixel's last flow event, or its own
    time where the pixel's run spans more than ``edge_run_px`` px of the edge's motion; walked
    back along the flow direction, at each step the newest of the pixels up to
    ``baseline_width_px`` beside it along the edge: a baseline of up to ``baseline_max_ms``,
    positions and times only), else from the flow's magnitude. They are
    assigned to square clusters (centre of mass, activity-weighted updates, growth, decay,
    removal below ``min_activity``). At every multiple of
    ``estimate_every_us`` each cluster's tau is the median of its recent samples, each moved
    forward at -1 s/s, fused with its prediction by a gated 1-D Kalman filter; a cluster whose
    tau reaches 0 is dropped. Series ``ttc`` (t, tau_s, cluster, x, y, support) holds the
    obstacle's cluster per tick (``select``: nearest the FOE, or most active; optionally only
    clusters off the road plane (``ground_test``: tau * dy below the road's constant
    K = f h / V, estimated from the events), inside a driving corridor, held between ticks),
    series ``ttc_clusters`` (t, cluster, x, y, size_px, tau_s, support, ground_ratio) every
    live cluster (ground_ratio = median(tau * dy) / K over its samples within 20 % of its
    last measurement where at least ``min_samples`` are, else over all its recent samples; -1
    while K is unknown). Both place a
    cluster at the median position of its recent samples whose tau lies within 20 % of its
    last measurement (where its TTC comes from; its square's centre until it has one).

    Only a credible cluster can be the obstacle: its recent samples agree (relative spread
    1.4826 MAD / median at most ``max_rel_spread``; the samples of one approaching surface
    share one TTC up to the flow's error, those of rotational flow read as expansion, or of
    several objects in one square, do not), the newest sample of its last measurement is no
    older than its tau (a tau predicted forward over more than the time left to contact rests
    on no data) and its tau lies within what the per-event bounds allow (at least
    ``min_tau_s``; the image speed it implies at the cluster, its distance from the FOE over
    tau, at most ``max_speed_pxs``: the forward prediction and the fusion can leave both). A
    tick without one emits no row; ``metrics.ttc_filter`` counts the ticks, the TTCs and the
    ticks without one by reason (no FOE yet, no cluster, none credible, only road clusters)
    and the events that started no cluster because every slot held a live one (a new
    cluster never displaces a live one).

    Lengths in px and speeds in px/s left null follow the camera (their reference camera
    values times f / 380.6 px, ``camera_scale``: the same angle spans twice the px on a
    640x480 sensor with the same field of view); ``baseline_px``, a walk over the pixel grid,
    does not.
    """

    name = "ttc"
    consumes = FlowPacket
    produces = FlowPacket
    needs_series = (FOE,)
    adds_series = (TTC, TTC_CLUSTERS)

    class Params(FilterParams):
        estimate_every_us: int = Field(10_000, ge=1, description="period of the TTC output")
        region_b_half_width_px: float | None = Field(
            None, gt=0, description="region B: largest horizontal offset from the FOE, px; "
            "null: 60 px x f / 380.6 px")
        region_b_min_below_px: float = Field(
            0.0, description="region B: events at least this far below the FOE (y down), px "
            "of this camera (the default 0 holds on any)")
        min_distance_px: float | None = Field(
            None, ge=0, description="ignore events this close to the FOE (tau is "
            "ill-conditioned there), px; null: 5 px x f / 380.6 px. A far obstacle's lower "
            "edge lies a few px below the FOE (5 px on the reference camera at a TTC of 2-3 "
            "s, the FOE's row error well under a pixel there); chosen on the reference drive "
            "(the tuning set), where 8 px dropped the far car's bursts")
        min_speed_pxs: float | None = Field(None, ge=0, description="ignore slower flow, px/s; "
                                            "null: 2 px/s x f / 380.6 px")
        max_speed_pxs: float | None = Field(None, gt=0, description="ignore faster flow, px/s; "
                                            "null: 20000 px/s x f / 380.6 px")
        min_tau_s: float = Field(0.02, ge=0, description="ignore per-event tau below this")
        max_tau_s: float = Field(60.0, gt=0, description="ignore per-event tau above this")
        cluster_size_px: float | None = Field(None, gt=0, description="half-size of a new "
                                              "cluster, px; null: 6 px x f / 380.6 px")
        max_cluster_size_px: float | None = Field(
            None, gt=0, description="largest half-size, px (small: the obstacle is not "
            "swallowed by road clusters); null: 15 px x f / 380.6 px")
        join_margin_px: float | None = Field(
            None, ge=0, description="events this far outside a cluster's square still join it "
            "(and grow it), px; null: 4 px x f / 380.6 px")
        activity_tau_ms: float = Field(
            150.0, gt=0, description="decay of cluster activity (a far obstacle's slow edges "
            "give few flow events; with 100 ms its cluster drops below the selection and "
            "removal thresholds between them and restarts; 150 ms chosen on the reference "
            "drive and its variations)")
        min_activity: float = Field(2.0, gt=0, description="clusters whose decayed activity "
                                    "(events) falls below this are removed")
        max_clusters: int = Field(
            64, ge=1, le=1024, description="cluster slots; an event that would start a cluster "
            "while every slot holds a live one starts none (metrics.ttc_filter counts them). "
            "Enough that they rarely bind: at 640x480 with 500 ms activity memories up to 43 "
            "clusters lived at once (chosen on the evaluation's 640x480 cell; the reference "
            "drive from its start never fills 32, a start near the car can)")
        samples_per_cluster: int = Field(256, ge=4, description="ring of recent samples")
        sample_max_age_ms: float = Field(200.0, gt=0, description="samples older than this "
                                         "are not used")
        min_samples: int = Field(8, ge=1, description="samples needed for a cluster estimate")
        rel_noise_floor: float = Field(0.01, ge=0, description="measurement noise floor "
                                       "(fraction of tau)")
        process_noise_s2_per_s: float = Field(0.05, ge=0, description="Kalman process noise "
                                              "of tau (s^2 per s)")
        select: Literal["nearest_foe", "support"] = Field(
            "nearest_foe", description="which cluster is the obstacle: the one nearest the FOE "
            "with activity >= select_min_activity (the first thing in the driving corridor; "
            "ground clusters lie farther below), or the most active one (thesis)")
        select_min_activity: float = Field(5.0, ge=0, description="activity a cluster needs "
                                           "to be selected as the obstacle (nearest_foe)")
        gate_sigma: float = Field(3.0, gt=0, description="reject medians farther than this "
                                  "many sigma from the prediction (3 in a row restart)")
        ground_test: bool = Field(True, description="only clusters nearer than the road at "
                                  "their rows can be the obstacle: median(tau * dy) / K < 1 - "
                                  "ground_tolerance, K = f h / V estimated from the events")
        ground_tolerance: float = Field(0.1, gt=0, lt=0.5, description="relative band around "
                                        "K that counts as road (also K's mode window)")
        ground_memory_ms: float = Field(1000.0, gt=0, description="K is the mode of tau * dy "
                                        "over the events' votes, which fade with this memory")
        ground_min_events: int = Field(500, ge=1, description="events K must have seen before "
                                       "the ground test applies")
        corridor_half_width_h: float | None = Field(
            None, gt=0, description="only clusters reaching into the driving corridor can be "
            "the obstacle: lateral gap to the FOE <= this times the rows from the FOE to the "
            "cluster's lower edge (the corridor's half-width in camera heights); None: off")
        select_hold: bool = Field(False, description="keep the previous tick's obstacle "
                                  "while it still qualifies (no jumping between clusters)")
        baseline_px: int = Field(6, ge=0, le=64, description="per-event tau from where the "
                                 "edge was up to this many px earlier (the pixels' last flow "
                                 "times), not from the flow's magnitude; 0: from the flow. "
                                 "Px of the grid, not derived: the walk's quantisation (half a "
                                 "pixel at each end) is what the baseline averages")
        baseline_max_ms: float = Field(500.0, gt=0, description="longest baseline")
        baseline_width_px: int = Field(0, ge=0, le=8, description="baseline: at each step "
                                       "back also look at the pixels up to this far beside "
                                       "it along the edge and take the one that fired last (a "
                                       "far obstacle's edge crosses a row in bursts that "
                                       "cover only part of it); 0: the pixel straight behind")
        edge_run_px: float = Field(5.0, ge=0, description="the baseline compares the "
                                   "pixels' edge arrival times (the flow packet's t_edge: the "
                                   "start of each pixel's run of same-polarity events) while "
                                   "the run is no longer than the edge takes to cross this "
                                   "many px at the event's flow speed; a longer run holds "
                                   "several edges, and the event's own time is used. 0: "
                                   "always the events' own times. Px of the grid")
        ground_fallback: bool = Field(True, description="with no cluster off the road, select "
                                      "among all clusters (else: no obstacle at that tick)")
        max_rel_spread: float | None = Field(
            MAX_REL_SPREAD, gt=0, description="a cluster is credible (can be the obstacle) "
            "only when the relative spread of its recent samples, 1.4826 MAD / median, is at "
            "most this; null: any spread")

    def reset(self) -> None:
        self._state = None
        self._ticks = self._rows = 0

    def params_on(self, g: Geometry) -> Params:
        """The parameters on the camera ``g``: those left null derived from its focal length."""
        p = self.params
        return p.model_copy(update={
            "region_b_half_width_px": derived(p.region_b_half_width_px, 60.0, g),
            "min_distance_px": derived(p.min_distance_px, 5.0, g),
            "min_speed_pxs": derived(p.min_speed_pxs, 2.0, g),
            "max_speed_pxs": derived(p.max_speed_pxs, 20_000.0, g),
            "cluster_size_px": derived(p.cluster_size_px, 6.0, g),
            "max_cluster_size_px": derived(p.max_cluster_size_px, 15.0, g),
            "join_margin_px": derived(p.join_margin_px, 4.0, g)})

    def _constants(self, g: Geometry):
        """The kernel's constants for the sensor geometry ``g``."""
        from evchain.kernels.records import record
        from evchain.kernels.ttc import TtcParams

        p = self.params_on(g)
        return record(
            TtcParams, period_us=p.estimate_every_us, select_nearest=p.select == "nearest_foe",
            select_min_activity=p.select_min_activity, half_width=p.region_b_half_width_px,
            min_below=p.region_b_min_below_px, min_dist=p.min_distance_px,
            min_speed=p.min_speed_pxs, max_speed=p.max_speed_pxs, min_tau=p.min_tau_s,
            max_tau=p.max_tau_s, init_size=p.cluster_size_px, max_size=p.max_cluster_size_px,
            join_margin=p.join_margin_px, act_tau_us=p.activity_tau_ms * 1000.0,
            min_activity=p.min_activity, max_age_us=p.sample_max_age_ms * 1000.0,
            min_samples=p.min_samples, rel_floor=p.rel_noise_floor,
            q_s2_per_s=p.process_noise_s2_per_s, gate=p.gate_sigma, ground_test=p.ground_test,
            ground_tol=p.ground_tolerance, ground_memory_us=p.ground_memory_ms * 1000.0,
            ground_min_events=p.ground_min_events, ground_fallback=p.ground_fallback,
            corridor=p.corridor_half_width_h or 0.0, hold=p.select_hold,
            base_px=p.baseline_px, base_age_us=p.baseline_max_ms * 1000.0,
            base_width=p.baseline_width_px, run_px=p.edge_run_px,
            max_spread=math.inf if p.max_rel_spread is None else p.max_rel_spread,
            f=g.f or 0.0, cx=g.cx, cy=g.cy)

    def process(self, packet: FlowPacket) -> FlowPacket:
        if not isinstance(packet, FlowPacket):
            raise DataError(f"ttc needs a FlowPacket, got {type(packet).__name__}")
        from evchain.kernels import ttc as kern

        p = self.params
        period = int(p.estimate_every_us)
        if self._state is None:
            g = packet.geometry
            self._prm = self._constants(g)
            self._state = kern.new_state(p.max_clusters, p.samples_per_cluster, g.height,
                                         g.width, p.baseline_px > 0)
            kern.start(self._state, -(-packet.t_start // period) * period)
        foe = packet.series.get("foe")
        if foe is None:
            foe = np.zeros(0, FOE.dtype)
        rotating = foe["rotation"] > 0
        entries = (np.ascontiguousarray(foe["t"], np.int64),
                   np.ascontiguousarray(foe["x"], np.float64),
                   np.ascontiguousarray(foe["y"], np.float64),
                   *(np.where(rotating, np.radians(foe[c].astype(np.float64)), 0.0)
                     for c in ROTATION_FIELDS),
                   (foe["rotation"] == 2).astype(np.float64))
        n_ticks = max(0, -(-(packet.t_end - kern.next_tick(self._state)) // period))
        ttc = np.zeros(n_ticks, TTC_DTYPE)
        cl = np.zeros(n_ticks * p.max_clusters, CLUSTER_DTYPE)
        no, nc = kern.process((packet.x, packet.y, packet.t, packet.p, packet.vx, packet.vy,
                               packet.t_edge),
                              entries, self._state, self._prm, int(packet.t_end), ttc, cl)
        self._ticks += n_ticks
        self._rows += no
        return packet.with_series("ttc", ttc[:no].copy()).with_series("ttc_clusters",
                                                                       cl[:nc].copy())

    def flush(self):
        from evchain.kernels import ttc as kern

        why = {"no FOE yet": 0, "no cluster": 0, "no credible cluster": 0,
               "only road clusters": 0}
        slotless = 0
        if self._state is not None:
            n = kern.no_ttc_counts(self._state)
            why = {"no FOE yet": n["no_foe"], "no cluster": n["no_cluster"],
                   "no credible cluster": n["not_credible"], "only road clusters": n["on_road"]}
            slotless = kern.slotless_events(self._state)
        self.context.metrics[self.metrics_key("ttc_filter")] = {
            "ticks": self._ticks, "estimates": self._rows, "no_estimate": why,
            "events_without_a_slot": slotless}
        return None
