"""`compare_events` / `nearest_dt` (evchain/benchmarks/scene_bands.py): two event streams of
one sensor compared event by event."""

import numpy as np
import pytest

from evchain.benchmarks.scene_bands import compare_events, nearest_dt
from evchain.core.packets import EventPacket, Geometry

G = Geometry(8, 6)


def packet(x, y, t, p):
    order = np.argsort(t, kind="stable")
    return EventPacket(geometry=G, t_start=0, t_end=int(np.max(t, initial=0)) + 1,
                       x=np.asarray(x, np.uint16)[order], y=np.asarray(y, np.uint16)[order],
                       t=np.asarray(t, np.int64)[order], p=np.asarray(p, np.int8)[order])


def random_events(rng, n):
    return packet(rng.integers(0, 8, n), rng.integers(0, 6, n), rng.integers(0, 5000, n),
                  rng.choice([-1, 1], n))


def slow_nearest(a, b):
    """For each event of b, |t_b - t_a| of the nearest event of a at its pixel and polarity."""
    out = []
    for xb, yb, tb, pb in zip(b.x, b.y, b.t, b.p, strict=True):
        same = (a.x == xb) & (a.y == yb) & (a.p == pb)
        if same.any():
            out.append(np.min(np.abs(a.t[same].astype(np.int64) - int(tb))))
    return np.array(out, np.float64)


@pytest.mark.parametrize("seed", range(5))
def test_nearest_dt_against_a_slow_reference(seed):
    rng = np.random.default_rng(seed)
    a, b = random_events(rng, 300), random_events(rng, 250)
    want = slow_nearest(a, b)
    got = nearest_dt(a, b)
    assert got["nearest_matched"] == len(want)
    assert got["nearest_median_abs_dt_us"] == pytest.approx(np.median(want))
    assert got["nearest_p95_abs_dt_us"] == pytest.approx(np.percentile(want, 95))


def test_a_lost_event_moves_no_other_match():
    """A pixel firing every ms, the second stream 3 µs later and missing its first event: the
    k-th matching pairs every later event with the previous crossing (~1 ms off), the nearest
    matching finds the 3 µs."""
    t = np.arange(10) * 1000
    a = packet(np.full(10, 2), np.full(10, 3), t, np.ones(10))
    b = packet(np.full(9, 2), np.full(9, 3), t[1:] + 3, np.ones(9))
    res = compare_events(a, b)
    assert res["median_abs_dt_us"] > 900
    assert res["nearest_median_abs_dt_us"] == 3.0
    assert res["nearest_matched"] == 9


def test_polarity_and_pixel_must_agree_and_empty_streams_give_none():
    a = packet([1], [1], [100], [1])
    b = packet([1, 2], [1, 1], [100, 100], [-1, 1])      # other polarity, other pixel
    assert nearest_dt(a, b)["nearest_matched"] == 0
    assert nearest_dt(a, b)["nearest_median_abs_dt_us"] is None
    empty = packet([], [], np.zeros(0, np.int64), [])
    assert nearest_dt(empty, a)["nearest_median_abs_dt_us"] is None
    assert nearest_dt(a, empty)["nearest_matched"] == 0
