"""Scorer throughput.

* ``scorer-flow``: ``flow_scorer`` in flow events/s, scoring a pure expansion whose flow carries
  Gaussian noise of a known size, so the AEE it must report is known analytically. Noise of
  ``NOISE_FRAC`` x the local speed on each component has a Rayleigh-distributed length with
  mean ``NOISE_FRAC * speed * sqrt(pi / 2)``; the row's error is the relative deviation of the
  scorer's AEE from that expectation (sampling noise, about 1/sqrt(events)).
* ``scorer-events``: ``event_scorer`` in events/s on random events over an approach whose
  obstacle fills the left half of the view, with no event in one 100 ms bin
  (:data:`GAP_US`): the bin sets ``obstacle_events_since_s`` exactly; the row's error is the
  reported value's distance from it, s.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_cpu_time, best_time
from evchain.core.packets import FlowPacket
from evchain.testing.contract import make_context, run_filter
from evchain.testing.synthetic import ExpansionTruth, approach_flow_packets

FOE = (60.0, 45.0)
TAU_S = 20.0  # time to collision at t = 0; the stream ends before it (at most 10 s)
NOISE_FRAC = 0.1


def _timed(cls, packets, truth, key: str) -> tuple[dict, float, float]:
    """The scorer ``cls`` (defaults) on ``packets`` against ``truth``: its ``metrics[key]``,
    best wall time and CPU time of a whole run (set-up, packets, flush)."""
    got: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        context = make_context(packets[0].geometry, truth, Path(tmp))

        def stage():
            f = cls()
            f.id = cls.name
            f.setup(cls.Params(), context)
            run_filter(f, packets, check=False)
            got.update(context.metrics[key])

        return got, best_time(stage), best_cpu_time(stage)


def flow_scorer(quick: bool) -> list[BenchRow]:
    from evchain.filters.flow_scorer import FlowScorer

    n = 200_000 if quick else 2_000_000
    duration_us = n * 5  # 200 k flow events/s of stream time, 20 ms packets
    packets = approach_flow_packets(FOE, TAU_S, n, duration_us=duration_us,
                                    n_packets=duration_us // 20_000, noise_frac=NOISE_FRAC,
                                    tau_shrinks=True)
    truth = ExpansionTruth(FOE, t_collision_s=TAU_S)
    flow = FlowPacket.concat(packets)
    speed = np.hypot(flow.x - FOE[0], flow.y - FOE[1]) / truth.ttc(flow.t)
    expected_aee = NOISE_FRAC * math.sqrt(math.pi / 2) * float(speed.mean())
    got, t_stage, cpu = _timed(FlowScorer, packets, truth, "flow")
    error = abs(got["aee_pxs"] / expected_aee - 1)
    return [BenchRow("scorer-flow", "flow_scorer", n / t_stage, "events/s", error,
                     "rel. deviation of AEE", None,
                     {"events": n, "aee_pxs": got["aee_pxs"], "expected_aee_pxs": expected_aee,
                      "cpu_time_eps": n / cpu},
                     data=f"synthetic expansion flow {n / 1e6:g} M events, "
                          f"{NOISE_FRAC * 100:g} % Gaussian noise")]


#: event_scorer's row: contact after CONTACT_S; no event in GAP_US (true TTC 2.0-1.9 s), so the
#: covered bins up to the end start at a true TTC of 1.9 s
CONTACT_S = 4.0
GAP_US = (2_000_000, 2_100_000)
EXPECTED_SINCE_S = 1.9


class _HalfObstacle(ExpansionTruth):
    """An approach whose obstacle (id 1) fills x < 120; elsewhere the road (id 0)."""

    obstacle_ids = np.array([1], np.int64)

    def object_id(self, x, y, t_us):
        return (np.asarray(x, np.float64) < 120).astype(np.int64)


def event_scorer(quick: bool) -> list[BenchRow]:
    from evchain.bench import cut_every
    from evchain.core.packets import EventPacket, Geometry
    from evchain.filters.event_scorer import EventScorer

    n = 200_000 if quick else 2_000_000
    g = Geometry(240, 180)
    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(0, int(CONTACT_S * 1e6), n))
    t = t[(t < GAP_US[0]) | (t >= GAP_US[1])]
    m = len(t)
    ev = EventPacket(geometry=g, t_start=0, t_end=int(CONTACT_S * 1e6),
                     x=rng.integers(0, g.width, m).astype(np.uint16),
                     y=rng.integers(0, g.height, m).astype(np.uint16), t=t,
                     p=rng.choice(np.array([-1, 1], np.int8), m))
    packets = cut_every(ev, 20_000)
    got, t_stage, cpu = _timed(EventScorer, packets, _HalfObstacle(FOE, CONTACT_S), "events")
    error = abs(got["obstacle_events_since_s"] - EXPECTED_SINCE_S)
    return [BenchRow("scorer-events", "event_scorer", m / t_stage, "events/s", error,
                     "|obstacle_events_since_s - 1.9 s| (s)", None,
                     {"events": m, "obstacle_events_since_s": got["obstacle_events_since_s"],
                      "obstacle_events_coverage": got["obstacle_events_coverage"],
                      "cpu_time_eps": m / cpu},
                     data=f"random events {m / 1e6:.3g} M over a 4 s approach, 240x180, the "
                          "obstacle the left half, one 100 ms bin without events")]


WORKLOADS = {"scorer-flow": flow_scorer, "scorer-events": event_scorer}
