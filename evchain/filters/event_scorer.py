"""Scorer ``event_scorer``: what the event stream itself shows of the obstacle before contact."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.obstacle_flow import ObstacleFlow
from evchain.core.packets import EventPacket
from evchain.core.truth import ObjectTruth, TtcTruth


class EventScorer(Filter):
    """Counts the events on the obstacle before contact: the bound for any flow stage after it.

    Placed before the flow stage, it counts per ``bin_us`` the events whose pixel shows the
    obstacle (the truth's object ids) while the true TTC is at most ``obstacle_window_s``, as
    ``flow_scorer`` counts flow events there (:mod:`evchain.core.obstacle_flow`). At the end
    ``metrics.events`` (``metrics.events@ID`` for a stage with an ``id``) holds
    ``obstacle_events_since_s`` (from how many seconds of true TTC on every bin has events on
    the obstacle up to the end), ``obstacle_events_coverage`` (the share of such bins in the
    window), ``obstacle_n_events`` and ``n_events``. A flow stage cannot cover a bin without
    events, so ``flow.obstacle_flow_since_s`` is at most ``events.obstacle_events_since_s``
    with the same window and bins. Without an obstacle (or a truth without object ids and a
    TTC) only ``n_events`` is given. Packets pass through unchanged.
    """

    name = "event_scorer"
    scorer = True
    consumes = EventPacket
    produces = None
    uses_truth = (ObjectTruth, TtcTruth)

    class Params(FilterParams):
        bin_us: int = Field(100_000, gt=0, description="bin of the obstacle's coverage (µs), as "
                            "flow_scorer's")
        obstacle_window_s: float = Field(
            3.0, gt=0, description="events on the obstacle are counted while its true TTC is at "
            "most this (s), as flow_scorer's; a bin of bin_us with at least one event on it is "
            "covered")

    def reset(self) -> None:
        self.obstacle = ObstacleFlow(getattr(self, "truth", None), self.params.obstacle_window_s,
                                     self.params.bin_us)
        self.n_events = 0
        self.span: list[int] | None = None

    def process(self, packet: EventPacket) -> EventPacket:
        if self.span is None:
            self.span = [packet.t_start, packet.t_end]
        self.span[1] = packet.t_end
        self.n_events += len(packet)
        self.obstacle.add(packet.x, packet.y, packet.t, np.full(len(packet), np.nan))
        return packet

    def flush(self) -> None:
        m: dict = {"n_events": self.n_events}
        if self.span is not None and self.obstacle.enabled:
            ob = self.obstacle.metrics(*self.span)
            m["obstacle_window_s"] = ob.get("obstacle_window_s")
            m["obstacle_events_since_s"] = ob.get("obstacle_flow_since_s")
            m["obstacle_events_coverage"] = ob.get("obstacle_flow_coverage")
            m["obstacle_n_events"] = ob.get("obstacle_n_flow")
            why = ob.get("why_none", {}).get("obstacle_flow_since_s")
            if why is not None:
                m["why_none"] = {"obstacle_events_since_s": why}
        self.context.metrics[self.metrics_key("events")] = m
        return None
