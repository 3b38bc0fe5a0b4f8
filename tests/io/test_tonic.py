"""tonic conversions both ways, checked against tonic itself where it is installed."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.packets import EventPacket, Geometry
from evchain.errors import DataError
from evchain.io.hdf5 import read_hdf5, write_hdf5
from evchain.io.tonic import (
    TONIC_DTYPE,
    from_tonic,
    packets_from_tonic,
    sensor_size,
    to_tonic,
)
from evchain.testing.synthetic import random_events

G = Geometry(64, 48)


def same(a, b):
    return all(np.array_equal(getattr(a, c), getattr(b, c)) for c in ("x", "y", "t", "p"))


def test_round_trip_and_dtype_is_tonics():
    ev = random_events(2000, G, 100, 90_000, seed=1)
    arr = to_tonic(ev)
    assert arr.dtype == TONIC_DTYPE
    assert np.array_equal(arr["p"], ev.p > 0)
    back = from_tonic(arr, sensor_size(G), ev.t_start, ev.t_end)
    assert same(back, ev) and (back.t_start, back.t_end) == (ev.t_start, ev.t_end)
    tonic_io = pytest.importorskip("tonic.io")
    assert TONIC_DTYPE == tonic_io.events_struct
    made = tonic_io.make_structured_array(arr["x"], arr["y"], arr["t"], arr["p"])
    assert same(from_tonic(made, sensor_size(G)), ev)


def test_to_frame_puts_each_polarity_in_its_channel():
    """tonic's ToFrame on converted events: ON events in channel 1, OFF in channel 0, counts
    per pixel exact."""
    transforms = pytest.importorskip("tonic.transforms")
    x = np.array([3, 3, 10, 20, 20, 20], np.uint16)
    y = np.array([4, 4, 5, 30, 30, 31], np.uint16)
    p = np.array([1, 1, -1, -1, 1, -1], np.int8)
    ev = EventPacket(geometry=G, t_start=0, t_end=100, x=x, y=y,
                     t=np.arange(6, dtype=np.int64) * 10, p=p)
    frames = transforms.ToFrame(sensor_size=sensor_size(G), event_count=len(ev))(to_tonic(ev))
    assert frames.shape == (1, 2, 48, 64)
    on, off = np.zeros((48, 64), int), np.zeros((48, 64), int)
    np.add.at(on, (y[p > 0], x[p > 0]), 1)
    np.add.at(off, (y[p < 0], x[p < 0]), 1)
    assert np.array_equal(frames[0, 1], on) and np.array_equal(frames[0, 0], off)
    assert on[4, 3] == 2 and off[5, 10] == 1 and on[30, 20] == 1 and off[30, 20] == 1


def test_a_tonic_transform_and_back_into_a_pipeline(tmp_path):
    """Apply a tonic transform, convert back, and hand the result to the hdf5 source's file."""
    transforms = pytest.importorskip("tonic.transforms")
    ev = random_events(500, G, 0, 50_000, seed=2)
    flipped = transforms.RandomFlipLR(sensor_size=sensor_size(G), p=1.0)(to_tonic(ev))
    back = from_tonic(flipped, sensor_size(G))
    assert np.array_equal(back.x, G.width - 1 - ev.x) and np.array_equal(back.p, ev.p)
    assert same(read_hdf5(write_hdf5(tmp_path / "e.h5", back, compression="gzip")), back)


def test_dataset_style_dtypes_convert():
    """Many tonic datasets use plain ints in another field order, p 0/1."""
    ev = random_events(300, G, seed=3)
    arr = np.zeros(len(ev), [("t", int), ("x", int), ("y", int), ("p", int)])
    arr["t"], arr["x"], arr["y"], arr["p"] = ev.t, ev.x, ev.y, ev.p > 0
    assert same(from_tonic(arr, G), ev)
    arr["p"] = ev.p  # -1/+1 too
    assert same(from_tonic(arr, G), ev)


def test_packets_from_tonic_cut_like_a_source():
    ev = random_events(1000, G, 1234, 51_000, seed=4)
    packets = list(packets_from_tonic(to_tonic(ev), sensor_size(G), packet_us=7000))
    assert [p.t_start for p in packets] == list(range(int(ev.t[0]), int(ev.t[-1]) + 1, 7000))
    assert packets[-1].t_end == int(ev.t[-1]) + 1
    assert same(EventPacket.concat(packets), ev)


def bad(**change):
    arr = to_tonic(random_events(5, G, seed=5))
    for name, (dtype, values) in change.items():
        fields = [(n, dtype if n == name else arr.dtype[n]) for n in arr.dtype.names]
        new = np.zeros(len(arr), fields)
        for n in arr.dtype.names:
            new[n] = values if n == name else arr[n]
        arr = new
    return arr


@pytest.mark.parametrize("arr, pattern", [
    (bad(t=(np.float64, [0.1, 0.2, 0.3, 0.4, 0.5])), "field t has dtype float64; expected "
     "integer µs"),
    (bad(p=(np.int8, [0, 1, 2, 1, 0])), r"tonic event 2: field p = 2; expected True/False"),
    (bad(p=(np.int8, [0, 1, -1, 1, 0])), "both 0 and -1"),
    (bad(x=(np.int16, [1, 2, 64, 3, 4])), "tonic event 2: field x = 64 is outside the 64x48"),
    (bad(y=(np.int16, [1, -2, 4, 3, 4])), "tonic event 1: field y = -2 is outside"),
    (bad(t=(np.int64, [5, 6, 4, 7, 8])), r"tonic event 2 at t = 4 us .*sort first"),
    (np.zeros(3, [("x", "i2"), ("y", "i2"), ("t", "i8")]), r"lack fields \['p'\]"),
])
def test_bad_input_names_the_field(arr, pattern):
    with pytest.raises(DataError, match=pattern):
        from_tonic(arr, sensor_size(G))
