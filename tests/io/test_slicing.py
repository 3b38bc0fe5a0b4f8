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


def _imu(t):
    from evchain.core.series import IMU

    t = np.asarray(t, np.int64)
    return IMU.array(t=t, ax=0.0, ay=-1.0, az=0.0, gx=t * 1e-3, gy=0.0, gz=0.0,
                     temperature_c=30.0)


def test_imu_slicer_hands_each_slice_its_samples():
    import pytest

    from evchain.errors import DataError
    from evchain.io.slicing import ImuSlicer

    g = Geometry(16, 16)
    ev = random_events(400, g, t_start=1000, t_end=9000, seed=3)
    packets = list(slice_stream(iter([{c: getattr(ev, c) for c in "xytp"}]), g, 700))
    t = np.arange(0, 12_000, 333)
    for cut in ([len(t)], [1, 5, 6, 30], list(range(1, len(t)))):   # how the file is read
        chunks = [_imu(c) for c in np.split(t, cut)]
        s = ImuSlicer(iter(chunks), "f.aedat4")
        out = [s.attach(p) for p in packets]
        s.finish()
        got = np.concatenate([p.series["imu"]["t"] for p in out])
        for p in out:
            st_ = p.series["imu"]["t"]
            assert np.all((st_ >= p.t_start) & (st_ < p.t_end))
        inside = t[(t >= packets[0].t_start) & (t < packets[-1].t_end)]
        np.testing.assert_array_equal(got, inside)
        assert s.before == np.count_nonzero(t < packets[0].t_start)
        assert s.after == np.count_nonzero(t >= packets[-1].t_end)
        assert s.delivered == len(inside) and s.read == len(t)
    back = ImuSlicer(iter([_imu([1000, 2000]), _imu([3000, 2500])]), "f.aedat4")
    with pytest.raises(DataError, match=r"f\.aedat4: IMU sample 3: timestamp goes backwards"):
        [back.attach(p) for p in packets]
