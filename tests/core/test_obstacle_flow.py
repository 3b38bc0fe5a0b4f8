"""Flow on the obstacle before contact (evchain.core.obstacle_flow), alone and in flow_scorer."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.obstacle_flow import ObstacleFlow
from evchain.core.packets import FlowPacket, Geometry
from evchain.filters.flow_scorer import FlowScorer

G = Geometry(100, 20)
CONTACT_US = 4_000_000  # contact 4 s into the stream


class ObstacleTruth:
    """The obstacle (id 7) fills x < 50; the road (id 1) the rest; true flow (10, 0) px/s;
    contact at CONTACT_US."""


    def __init__(self, ids=(7,)):
        self.obstacle_ids = np.array(ids, np.int64)

    def flow(self, x, y, t_us):
        n = np.shape(x)
        return np.full(n, 10.0), np.zeros(n)

    def ttc(self, t_us):
        tau = (CONTACT_US - np.asarray(t_us, np.float64)) * 1e-6
        return np.where(tau > 0, tau, np.nan)

    def object_id(self, x, y, t_us):
        return np.where(np.asarray(x, np.float64) < 50, 7, 1).astype(np.int64)


def counter(window_s=3.0, truth=None):
    return ObstacleFlow(truth if truth is not None else ObstacleTruth(), window_s, 100_000)


def one_per_bin(times_us, x=10.0, err=0.1):
    t = np.asarray(times_us, np.int64)
    n = len(t)
    return np.full(n, x), np.zeros(n), t, np.full(n, err)


def test_every_bin_covered_gives_the_whole_window():
    c = counter()
    c.add(*one_per_bin(np.arange(1_000_000, 4_000_000, 100_000) + 50_000))
    m = c.metrics(0, CONTACT_US)
    assert m["obstacle_flow_since_s"] == pytest.approx(3.0)
    assert m["obstacle_flow_coverage"] == 1.0
    assert m["obstacle_window_s"] == pytest.approx(3.0)
    assert m["obstacle_n_flow"] == 30
    assert m["obstacle_ree_normal_pct"] == pytest.approx(10.0)
    assert m["obstacle_outliers_ree_normal50"] == 0.0
    assert [b["ttc_s"] for b in m["obstacle_by_ttc"]] == [[2, 3], [1, 2], [0, 1]]
    assert all(b["obstacle_n_flow"] == 10 for b in m["obstacle_by_ttc"])


def test_a_gap_cuts_the_run_and_off_obstacle_events_do_not_count():
    c = counter()
    times = np.arange(1_000_000, 4_000_000, 100_000) + 50_000
    keep = times != 2_450_000  # the bin [2.4, 2.5) s, TTC 1.6-1.5 s, has none on the obstacle
    c.add(*one_per_bin(times[keep]))
    c.add(*one_per_bin([2_450_000], x=80.0))  # on the road: not the obstacle
    c.add(*one_per_bin([500_000]))  # TTC 3.5 s: outside the window
    m = c.metrics(0, CONTACT_US)
    assert m["obstacle_flow_since_s"] == pytest.approx(1.5)
    assert m["obstacle_flow_coverage"] == pytest.approx(29 / 30)
    assert m["obstacle_n_flow"] == 29


def test_errors_and_outliers_per_band():
    c = counter()
    t = np.array([1_050_000, 1_150_000, 3_950_000])
    c.add(np.full(3, 10.0), np.zeros(3), t, np.array([2.0, np.nan, 0.2]))
    m = c.metrics(0, CONTACT_US)
    assert m["obstacle_n_flow"] == 3
    assert m["obstacle_ree_normal_pct"] == pytest.approx(110.0)  # NaN not averaged
    assert m["obstacle_outliers_ree_normal50"] == pytest.approx(0.5)
    far, _, near = m["obstacle_by_ttc"]
    assert far["obstacle_n_flow"] == 2 and far["obstacle_ree_normal_pct"] == pytest.approx(200)
    assert near["obstacle_ree_normal_pct"] == pytest.approx(20.0)
    assert m["obstacle_far_ree_normal_pct"] == pytest.approx(200.0)
    assert m["obstacle_flow_since_s"] == pytest.approx(0.1)  # only the last bin reaches the end


def test_last_bin_empty_gives_zero_and_short_stream_says_its_window():
    c = counter()
    c.add(*one_per_bin([3_000_000 + 50_000]))
    m = c.metrics(2_500_000, CONTACT_US)
    assert m["obstacle_flow_since_s"] == 0.0
    assert m["obstacle_far_ree_normal_pct"] is None  # nothing at TTC 3-2 s: the stream starts later
    assert "true TTC of 2-3 s" in m["why_none"]["obstacle_far_ree_normal_pct"]
    assert m["obstacle_window_s"] == pytest.approx(1.5)  # the stream starts 1.5 s before contact
    assert [b["ttc_s"] for b in m["obstacle_by_ttc"]] == [[1, 2], [0, 1]]


def test_no_window_no_obstacle_no_objects():
    c = counter()
    m = c.metrics(0, 500_000)  # TTC 4-3.5 s: never within 3 s
    assert m["obstacle_flow_since_s"] is None
    assert "never within 3 s" in m["why_none"]["obstacle_flow_since_s"]
    assert counter().metrics(10, 10)["obstacle_flow_since_s"] is None
    assert counter(truth=ObstacleTruth(ids=())).metrics(0, CONTACT_US) == {}

    class FlowOnly:
        def flow(self, x, y, t_us):
            return np.zeros(np.shape(x)), np.zeros(np.shape(x))

    empty = ObstacleFlow(FlowOnly(), 3.0, 100_000)
    empty.add(*one_per_bin([3_500_000]))
    assert empty.metrics(0, CONTACT_US) == {}


def test_bins_do_not_depend_on_packet_cuts():
    rng = np.random.default_rng(3)
    t = np.sort(rng.integers(0, CONTACT_US, 500))
    x = rng.uniform(0, 100, 500)
    err = rng.exponential(0.4, 500)
    whole, parts = counter(), counter()
    whole.add(x, np.zeros(500), t, err)
    for a, b in [(0, 17), (17, 230), (230, 231), (231, 500)]:
        parts.add(x[a:b], np.zeros(b - a), t[a:b], err[a:b])
    assert whole.metrics(0, CONTACT_US) == parts.metrics(0, CONTACT_US)


def test_flow_scorer_reports_it():
    f = FlowScorer()
    ctx = Context(geometry=G, truth=ObstacleTruth())
    f.setup(FlowScorer.Params(obstacle_window_s=2.0), ctx)
    for start in range(0, CONTACT_US, 500_000):
        t = np.arange(start, start + 500_000, 100_000, dtype=np.int64) + 10
        n = len(t)
        f.process(FlowPacket(geometry=G, t_start=start, t_end=start + 500_000,
                             x=np.full(n, 5, np.uint16), y=np.zeros(n, np.uint16), t=t,
                             p=np.ones(n, np.int8), vx=np.full(n, 12.0, np.float32),
                             vy=np.zeros(n, np.float32)).validate())
    f.flush()
    m = ctx.metrics["flow"]
    assert m["obstacle_flow_since_s"] == pytest.approx(2.0)
    assert m["obstacle_n_flow"] == 20
    assert m["obstacle_ree_normal_pct"] == pytest.approx(20.0)
