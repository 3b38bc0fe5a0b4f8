import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from evchain.core.packets import EventPacket, Geometry
from evchain.io.slicing import slice_as_delivered, slice_stream
from evchain.testing.synthetic import random_events

EV = random_events(300, Geometry(16, 16), 0, 10_000, seed=5)
COLS = {c: getattr(EV, c) for c in EventPacket.columns}


def packets(cuts):
    edges = [0, *sorted(set(cuts)), len(EV)]
    chunks = ({c: v[a:b] for c, v in COLS.items()}
              for a, b in zip(edges[:-1], edges[1:], strict=True))
    return list(slice_stream(chunks, EV.geometry, 700))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, len(EV)), max_size=12))
def test_chunk_boundaries_do_not_change_packets(cuts):
    got, ref = packets(cuts), packets([])
    assert [(p.t_start, p.t_end) for p in got] == [(p.t_start, p.t_end) for p in ref]
    for a, b in zip(got, ref, strict=True):
        assert np.array_equal(a.t, b.t) and np.array_equal(a.x, b.x)


def test_slices_cover_the_stream():
    ps = packets([])
    assert ps[0].t_start == EV.t[0] and ps[-1].t_end == EV.t[-1] + 1
    assert sum(len(p) for p in ps) == len(EV)
    assert all(p.t_end - p.t_start <= 700 for p in ps)
    assert list(slice_stream(iter([]), EV.geometry, 700)) == []


def chunked(cuts, cols=COLS):
    n = len(cols["t"])
    edges = [0, *sorted(set(cuts)), n]
    return [{c: v[a:b] for c, v in cols.items()} for a, b in zip(edges[:-1], edges[1:],
                                                                  strict=True)]


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, len(EV)), max_size=12))
def test_as_delivered_keeps_every_event_in_consecutive_slices(cuts):
    chunks = chunked(cuts)
    ps = list(slice_as_delivered(iter(chunks), EV.geometry))
    for i, p in enumerate(ps):
        p.validate(f"packet {i}")
        assert i == 0 or p.t_start == ps[i - 1].t_end
    whole = EventPacket.concat(ps)
    for c in EventPacket.columns:
        assert np.array_equal(getattr(whole, c), COLS[c])
    assert ps[0].t_start == EV.t[0] and ps[-1].t_end == EV.t[-1] + 1
    # a packet as soon as its chunk came: it ends at that chunk's last time
    ends = {int(ch["t"][-1]) for ch in chunks if len(ch["t"])}
    assert all(p.t_end in ends for p in ps[:-1])


def test_as_delivered_holds_events_at_a_chunks_last_time():
    t = np.array([5, 7, 7, 7, 9, 9, 12], np.int64)
    cols = {"x": np.arange(7, dtype=np.uint16), "y": np.zeros(7, np.uint16), "t": t,
            "p": np.ones(7, np.int8)}
    chunks = chunked([2, 3, 5], cols)  # [5 7] [7] [7 9] [9 12]
    ps = list(slice_as_delivered(iter(chunks), EV.geometry))
    assert [(p.t_start, p.t_end, p.t.tolist()) for p in ps] == [
        (5, 7, [5]), (7, 9, [7, 7, 7]), (9, 12, [9, 9]), (12, 13, [12])]
    assert list(slice_as_delivered(iter([]), EV.geometry)) == []
