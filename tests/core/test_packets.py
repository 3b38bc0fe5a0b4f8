import numpy as np
import pytest

from evchain import DataError, EventPacket, FlowPacket, FramePacket, Geometry
from evchain.testing.synthetic import random_events, textured_frames

G = Geometry(32, 24)


def test_geometry_defaults_and_errors():
    g = Geometry(320, 240, f=380.6)
    assert (g.cx, g.cy, g.shape) == (159.5, 119.5, (240, 320))
    with pytest.raises(DataError, match="positive"):
        Geometry(0, 10)


def test_structured_round_trip():
    ev = random_events(50, G)
    back = EventPacket.from_structured(ev.to_structured(), G, ev.t_start, ev.t_end)
    for name in EventPacket.columns:
        assert np.array_equal(getattr(back, name), getattr(ev, name))
        assert getattr(back, name).dtype == np.dtype(EventPacket.columns[name])


def test_structured_missing_field():
    arr = np.zeros(3, dtype=[("x", "u2"), ("y", "u2"), ("t", "i8")])
    with pytest.raises(DataError, match="lacks fields"):
        EventPacket.from_structured(arr, G)


@pytest.mark.parametrize("change, message", [
    (dict(x=np.array([40], np.uint16)), "outside the 32x24 sensor"),
    (dict(t=np.array([5], np.int64)), "outside the slice"),
    (dict(p=np.array([0], np.int8)), "polarity"),
    (dict(x=np.array([1], np.int32)), "must be uint16"),
    (dict(y=np.array([1, 2], np.uint16)), "has 2 rows"),
])
def test_event_invariants(change, message):
    base = dict(x=np.array([1], np.uint16), y=np.array([1], np.uint16),
                t=np.array([15], np.int64), p=np.array([1], np.int8))
    base.update(change)
    with pytest.raises(DataError, match=message):
        EventPacket(geometry=G, t_start=10, t_end=20, **base).validate()


def test_decreasing_time_named():
    ev = EventPacket(geometry=G, t_start=0, t_end=20, x=np.zeros(2, np.uint16),
                     y=np.zeros(2, np.uint16), t=np.array([9, 3], np.int64),
                     p=np.ones(2, np.int8))
    with pytest.raises(DataError, match="event 1 at 3 us follows 9 us"):
        ev.validate("here")


def test_frame_invariants():
    fr = textured_frames(3, G)
    fr.validate()
    with pytest.raises(DataError, match="finite"):
        fr.replace(frames=fr.frames * np.float32(np.nan)).validate()
    with pytest.raises(DataError, match="shape"):
        fr.replace(frames=fr.frames[:, :, :5]).validate()
    with pytest.raises(DataError, match="must increase"):
        fr.replace(t=fr.t[::-1].copy()).validate()


def test_flow_finite_and_concat():
    ev = random_events(10, G, 0, 100)
    flow = FlowPacket.from_events(ev, np.arange(10), np.ones(10), np.zeros(10))
    flow.validate()
    with pytest.raises(DataError, match="finite"):
        flow.replace(vx=np.full(10, np.inf, np.float32)).validate()
    a = random_events(5, G, 0, 100, seed=1)
    b = random_events(7, G, 100, 200, seed=2)
    both = EventPacket.concat([a, b]).validate()
    assert (len(both), both.t_start, both.t_end) == (12, 0, 200)


def test_flow_edge_arrival_defaults_to_the_event_time_and_never_follows_it():
    ev = random_events(10, G, 0, 100)
    flow = FlowPacket.from_events(ev, np.arange(3, 8), np.ones(5), np.zeros(5)).validate()
    np.testing.assert_array_equal(flow.t_edge, ev.t[3:8])
    arrival = ev.t - 7
    flow = FlowPacket.from_events(ev, np.arange(3, 8), np.ones(5), np.zeros(5), arrival)
    np.testing.assert_array_equal(flow.validate().t_edge, arrival[3:8])
    late = flow.t_edge.copy()
    late[2] = flow.t[2] + 1
    with pytest.raises(DataError, match="event 2's edge arrival"):
        flow.replace(t_edge=late).validate()
    assert FlowPacket.empty(G, 0, 10).validate().t_edge.dtype == np.int64
    both = FlowPacket.concat([flow, FlowPacket.empty(G, flow.t_end, flow.t_end)])
    np.testing.assert_array_equal(both.t_edge, arrival[3:8])


def test_empty_packets():
    e = EventPacket.empty(G, 5, 5).validate()
    assert len(e) == 0
    assert len(FramePacket.empty(G, 0, 10).validate()) == 0


def test_replace_copies_and_checks_field_names():
    g = Geometry(4, 3)
    a = EventPacket(geometry=g, t_start=0, t_end=10, x=np.array([1], np.uint16),
                    y=np.array([2], np.uint16), t=np.array([5], np.int64),
                    p=np.array([1], np.int8))
    b = a.replace(t_end=20)
    assert type(b) is EventPacket and b.t_end == 20 and a.t_end == 10 and b.x is a.x
    c = b.with_series("foe", np.zeros(0, [("t", "i8")]))
    assert "foe" in c.series and "foe" not in b.series
    with pytest.raises(TypeError):
        a.replace(nope=1)
