"""The example plugin's own tests: kernel vs naive reference, behaviour, registration, contract."""

from __future__ import annotations

import numpy as np
import pytest
from evchain_example.background_activity import NEVER, BackgroundActivityFilter
from hypothesis import given, settings
from hypothesis import strategies as st
from naive_background_activity import background_activity as naive  # tests/ is on sys.path

from evchain.core.packets import EventPacket, Geometry
from evchain.core.registry import make_registry
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import moving_edge_events, random_events


def kernel(ev: EventPacket, window: int) -> np.ndarray:
    from evchain_example.kernels import background_activity

    last = np.full(ev.geometry.shape, NEVER, np.int64)
    keep = np.empty(len(ev), np.bool_)
    background_activity(ev.x, ev.y, ev.t, last, window, keep)
    return keep


def as_list(ev):
    return list(zip(ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), strict=True))


@pytest.mark.parametrize("window", [0, 100, 5000])
def test_kernel_matches_naive_random(window):
    g = Geometry(12, 9)
    ev = random_events(3000, g, 0, 300_000, seed=window)
    got = kernel(ev, window).tolist()
    assert got == naive(as_list(ev), g.width, g.height, window)
    if window == 5000:
        assert 0 < sum(got) < len(got)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 2), st.integers(0, 40)),
                max_size=50), st.integers(0, 10))
def test_kernel_matches_naive_hard(raw, window):
    # a 4x3 sensor: every pixel is at a border; equal timestamps; window 0
    raw.sort(key=lambda e: e[2])
    g = Geometry(4, 3)
    ev = EventPacket(geometry=g, t_start=0, t_end=41, x=np.array([e[0] for e in raw], np.uint16),
                     y=np.array([e[1] for e in raw], np.uint16),
                     t=np.array([e[2] for e in raw], np.int64), p=np.ones(len(raw), np.int8))
    assert kernel(ev, window).tolist() == naive(raw, 4, 3, window)


def test_own_pixel_does_not_support_itself_but_a_neighbour_does():
    g = Geometry(10, 10)
    ev = EventPacket(geometry=g, t_start=0, t_end=100,
                     x=np.array([5, 5, 6, 3], np.uint16), y=np.array([5, 5, 6, 3], np.uint16),
                     t=np.array([0, 10, 20, 30], np.int64), p=np.ones(4, np.int8))
    # 1st: nothing before; 2nd: same pixel only; 3rd: diagonal neighbour 20 us ago; 4th: far
    assert kernel(ev, 50).tolist() == [False, False, True, False]
    assert kernel(ev, 5).tolist() == [False, False, False, False]


def test_removes_noise_keeps_edge():
    g = Geometry(64, 48)
    edge = moving_edge_events(300.0, 0.0, g, duration_us=150_000)
    noise = random_events(300, g, 0, 150_000, seed=1)
    cols = {c: np.concatenate([getattr(edge, c), getattr(noise, c)]) for c in EventPacket.columns}
    ev = EventPacket(geometry=g, t_start=0, t_end=150_000, **cols)
    order = np.argsort(ev.t, kind="stable")
    ev = ev.select(order)
    is_noise = np.concatenate([np.zeros(len(edge), bool), np.ones(len(noise), bool)])[order]
    keep = kernel(ev, 5000)
    assert keep[~is_noise].mean() > 0.9
    assert keep[is_noise].mean() < 0.2


def test_contract():
    ev = random_events(4000, Geometry(32, 24), 0, 100_000, seed=2)
    out = check_filter(BackgroundActivityFilter, {"window_us": 3000},
                       recut([ev], [25_000, 70_000]))
    assert 0 < len(out["t"]) < len(ev)


def test_registered_through_the_entry_point():
    registry = make_registry()
    info = registry.filters["background_activity"]
    assert info.cls is BackgroundActivityFilter
    assert info.distribution == "evchain-example"
    assert "background-activity" in registry.workloads
