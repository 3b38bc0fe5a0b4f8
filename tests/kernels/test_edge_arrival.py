"""The edge arrival kernel against its naive reference, on random and hard streams."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from evchain.core.edge_arrival import EdgeArrivals
from evchain.core.packets import EventPacket, Geometry
from tests.naive.edge_arrival import arrivals as naive

GEOMETRY = Geometry(8, 6)


def _packet(x, y, t, p):
    return EventPacket(geometry=GEOMETRY, t_start=int(t[0]) if len(t) else 0,
                       t_end=int(t[-1]) + 1 if len(t) else 0, x=np.asarray(x, np.uint16),
                       y=np.asarray(y, np.uint16), t=np.asarray(t, np.int64),
                       p=np.asarray(p, np.int8)).validate()


def _both(x, y, t, p, gap_us, cuts=()):
    """The kernel over the stream cut into packets at ``cuts``, and the naive reference."""
    tracker = EdgeArrivals(GEOMETRY.height, GEOMETRY.width, gap_us)
    bounds = [0, *sorted(cuts), len(t)]
    got = np.concatenate([tracker.of(_packet(x[a:b], y[a:b], t[a:b], p[a:b]))
                          for a, b in zip(bounds[:-1], bounds[1:], strict=True)])
    want = naive(list(zip(x, y, t, p, strict=True)), gap_us)
    return got, np.asarray(want, np.int64)


def test_random_streams_match_the_reference():
    rng = np.random.default_rng(5)
    for gap in (0, 1, 50, 1000, 10**9):
        n = 5000
        t = np.cumsum(rng.integers(0, 40, n))
        x, y = rng.integers(0, 8, n), rng.integers(0, 6, n)
        p = rng.choice([-1, 1], n, p=[0.3, 0.7])
        got, want = _both(x, y, t, p, gap, cuts=rng.integers(0, n, 7))
        np.testing.assert_array_equal(got, want)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 7), st.integers(0, 5), st.integers(0, 300),
                          st.sampled_from([-1, 1])), max_size=60),
       st.integers(0, 400), st.lists(st.integers(0, 60), max_size=3))
def test_any_stream_matches_the_reference(steps, gap, cuts):
    t = np.cumsum([s[2] for s in steps]).astype(np.int64)
    x = [s[0] for s in steps]
    y = [s[1] for s in steps]
    p = [s[3] for s in steps]
    got, want = _both(np.array(x, int), np.array(y, int), t, np.array(p, int), gap,
                      [c for c in cuts if c <= len(steps)])
    np.testing.assert_array_equal(got, want)


def test_runs_end_at_the_other_polarity_and_at_a_long_pause():
    # one pixel: ON ON (a run), OFF (new run), OFF after a pause of exactly the gap (same
    # run), OFF after a longer pause (new run), ON at the same time as the last OFF (new run)
    t = np.array([10, 20, 30, 130, 231, 231])
    p = np.array([1, 1, -1, -1, -1, 1])
    got, want = _both(np.zeros(6, int), np.zeros(6, int), t, p, 100)
    np.testing.assert_array_equal(got, [10, 10, 30, 30, 231, 231])
    np.testing.assert_array_equal(got, want)


def test_empty_packets_and_huge_times():
    tracker = EdgeArrivals(GEOMETRY.height, GEOMETRY.width, 1000)
    assert tracker.of(_packet([], [], [], [])).shape == (0,)
    big = 2**62
    got = tracker.of(_packet([1, 1], [2, 2], [big, big + 1], [1, 1]))
    np.testing.assert_array_equal(got, [big, big])
    # a first event at time 0 starts a run (no earlier event at the pixel)
    got = EdgeArrivals(6, 8, 10**18).of(_packet([3], [4], [0], [-1]))
    np.testing.assert_array_equal(got, [0])
