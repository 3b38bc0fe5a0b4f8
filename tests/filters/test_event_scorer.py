"""``event_scorer``: the events on the obstacle before contact, the bound of any flow stage."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.bench import cut_every
from evchain.core.packets import EventPacket, FlowPacket
from evchain.filters.event_scorer import EventScorer
from evchain.filters.flow_scorer import FlowScorer
from evchain.testing.contract import check_filter, make_context
from tests.core.test_obstacle_flow import CONTACT_US, G, ObstacleTruth


def _events(times_us, x):
    t = np.asarray(times_us, np.int64)
    n = len(t)
    return EventPacket(geometry=G, t_start=0, t_end=CONTACT_US,
                       x=np.asarray(x, np.uint16), y=np.zeros(n, np.uint16), t=t,
                       p=np.ones(n, np.int8))


def _metrics(cls, params, packets, truth):
    f = cls()
    f.id = cls.name
    ctx = make_context(G, truth)
    f.setup(cls.Params(**params), ctx)
    for p in packets:
        assert f.process(p) is p or cls is FlowScorer
    f.flush()
    return ctx.metrics


def test_a_bin_without_events_cuts_the_run_and_bounds_the_flow():
    """Events in every 100 ms bin of the last 3 s but one (TTC 1.6-1.5 s; a road event
    there does not count): since 1.5 s, 29 of 30 bins. A flow stage that kept every event
    covers no more."""
    times = np.arange(1_000_000, 4_000_000, 100_000) + 50_000
    on = np.where(times == 2_450_000, 80, 10)           # x 80: the road
    ev = _events(np.sort(np.r_[times, 500_000]), np.r_[10, on])
    m = _metrics(EventScorer, {}, cut_every(ev, 250_000), ObstacleTruth())["events"]
    assert m["n_events"] == 31
    assert m["obstacle_events_since_s"] == pytest.approx(1.5)
    assert m["obstacle_events_coverage"] == pytest.approx(29 / 30)
    assert m["obstacle_n_events"] == 29
    assert m["obstacle_window_s"] == pytest.approx(3.0)
    flow = FlowPacket.from_events(ev, np.arange(len(ev)), np.full(len(ev), 10.0),
                                  np.zeros(len(ev)))
    fm = _metrics(FlowScorer, {}, [flow], ObstacleTruth())["flow"]
    assert fm["obstacle_flow_since_s"] == m["obstacle_events_since_s"]


def test_without_an_obstacle_only_the_count_and_with_no_window_a_reason():
    ev = _events([100, 200, 300], [10, 10, 10])
    assert _metrics(EventScorer, {}, [ev], ObstacleTruth(ids=()))["events"] == {"n_events": 3}
    assert _metrics(EventScorer, {}, [ev], None)["events"] == {"n_events": 3}
    short = EventPacket(geometry=G, t_start=0, t_end=500_000, x=np.array([10], np.uint16),
                        y=np.zeros(1, np.uint16), t=np.array([100], np.int64),
                        p=np.ones(1, np.int8))
    m = _metrics(EventScorer, {}, [short], ObstacleTruth())["events"]  # TTC 4-3.5 s
    assert m["obstacle_events_since_s"] is None
    assert "never within 3 s" in m["why_none"]["obstacle_events_since_s"]
    empty = EventPacket.empty(G, 3_000_000, CONTACT_US)
    m = _metrics(EventScorer, {"obstacle_window_s": 1.0}, [empty], ObstacleTruth())["events"]
    assert m["n_events"] == 0 and m["obstacle_events_since_s"] == 0.0


def test_contract_packets_pass_unchanged():
    rng = np.random.default_rng(5)
    t = np.sort(rng.integers(0, CONTACT_US, 400))
    ev = _events(t, rng.integers(0, 100, 400))
    out = check_filter(EventScorer, {}, cut_every(ev, 300_000), truth=ObstacleTruth())
    assert np.array_equal(out["t"], ev.t) and np.array_equal(out["x"], ev.x)
