"""refractory: kernel against the naive reference, semantics, contract."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.filters.refractory import NEVER, Refractory
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import random_events
from tests.naive.refractory import refractory as naive

G = Geometry(8, 6)


def kernel(ev: EventPacket, period: int, per_polarity: bool) -> np.ndarray:
    from evchain.kernels.refractory import refractory

    last = np.full((2 if per_polarity else 1, *ev.geometry.shape), NEVER, np.int64)
    keep = np.empty(len(ev), np.bool_)
    refractory(ev.x, ev.y, ev.t, ev.p, last, period, per_polarity, keep)
    return keep


def as_list(ev):
    return list(zip(ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), ev.p.tolist(), strict=True))


@pytest.mark.parametrize("per_polarity", [False, True])
@pytest.mark.parametrize("period", [0, 1, 50, 5000])
def test_kernel_matches_naive_random(period, per_polarity):
    ev = random_events(4000, G, 0, 100_000, seed=period)  # many repeats per pixel
    assert kernel(ev, period, per_polarity).tolist() == naive(as_list(ev), period, per_polarity)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2), st.integers(0, 1), st.integers(0, 30),
                          st.sampled_from([-1, 1])), max_size=60),
       st.integers(0, 12), st.booleans())
def test_kernel_matches_naive_hard(raw, period, per_polarity):
    # few pixels, equal timestamps, zero period
    raw.sort(key=lambda e: e[2])
    ev = EventPacket(geometry=G, t_start=0, t_end=31,
                     x=np.array([e[0] for e in raw], np.uint16),
                     y=np.array([e[1] for e in raw], np.uint16),
                     t=np.array([e[2] for e in raw], np.int64),
                     p=np.array([e[3] for e in raw], np.int8))
    assert kernel(ev, period, per_polarity).tolist() == naive(raw, period, per_polarity)


def test_semantics():
    # pixel (1, 1): 0 passes, 500 blocked (does not extend), 1000 passes (exactly the period),
    # 1500 blocked; pixel (2, 1) independent; ON at 1600 blocked unless per_polarity
    x = [1, 1, 2, 1, 1, 1]
    t = [0, 500, 600, 1000, 1500, 1600]
    p = [-1, -1, -1, -1, -1, 1]
    ev = EventPacket(geometry=G, t_start=0, t_end=2000, x=np.array(x, np.uint16),
                     y=np.ones(6, np.uint16), t=np.array(t, np.int64), p=np.array(p, np.int8))
    assert kernel(ev, 1000, False).tolist() == [True, False, True, True, False, False]
    assert kernel(ev, 1000, True).tolist() == [True, False, True, True, False, True]


@pytest.mark.parametrize("per_polarity", [False, True])
def test_contract_and_state_across_packets(per_polarity):
    ev = random_events(3000, Geometry(32, 24), 0, 200_000, seed=3)
    params = {"period_us": 2000, "per_polarity": per_polarity}
    out = check_filter(Refractory, params, recut([ev], [50_000, 120_000]))
    expect = naive(as_list(ev), 2000, per_polarity)
    assert np.array_equal(out["t"], ev.t[np.array(expect)])
    assert 0 < len(out["t"]) < len(ev)


def test_filter_on_flow_packets_keeps_columns():
    from evchain.core.packets import FlowPacket

    ev = random_events(200, G, 0, 10_000, seed=1)
    flow = FlowPacket.from_events(ev, np.arange(len(ev)), np.ones(len(ev)), np.zeros(len(ev)))
    f = Refractory()
    f.setup(Refractory.Params(period_us=500), Context(geometry=G))
    out = f.process(flow)
    assert isinstance(out, FlowPacket) and len(out.vx) == len(out)
