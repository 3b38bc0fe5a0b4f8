import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from evchain.core.packets import EventPacket, Geometry
from evchain.io.slicing import slice_stream
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
