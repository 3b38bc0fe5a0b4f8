import math
import sys

import numpy as np
import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.filter import Filter
from evchain.core.packets import EventPacket, Geometry
from evchain.core.registry import make_registry
from evchain.errors import ConfigError, DataError, FilterError
from evchain.hookspecs import hookimpl
from evchain.io.hdf5 import Hdf5Writer, read_hdf5, write_hdf5
from evchain.testing.contract import check_source, make_context, run_filter
from evchain.testing.synthetic import random_events

h5py = pytest.importorskip("h5py")


def write_file(path, ev, width=64, height=48, p01=False):
    """A file as earlier evchain versions wrote it (p -1/+1, absolute t), or with p 0/1."""
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g.attrs.update({"width": width, "height": height})
        for c in ("x", "y", "t"):
            g[c] = getattr(ev, c)
        g["p"] = (ev.p > 0).astype(np.uint8) if p01 else ev.p


def same(a, b):
    return all(np.array_equal(getattr(a, c), getattr(b, c)) for c in ("x", "y", "t", "p"))


@pytest.mark.parametrize("block_events", [1 << 20, 1000])
def test_round_trip_through_pipeline(tmp_path, monkeypatch, block_events):
    """DSEC's layout written, identical events read back, whether the writer appends once at
    the end or in many blocks."""
    monkeypatch.setattr("evchain.io.hdf5.WRITE_BLOCK_EVENTS", block_events)
    ev = random_events(5000, t_start=0, t_end=95_000, seed=1)
    ev = ev.replace(t=ev.t + 1_600_000_000_000_000)  # a Unix time in µs, as DSEC's
    write_file(tmp_path / "in.h5", ev, p01=True)
    registry = make_registry()
    text = (f"chain:\n  - use: hdf5\n    path: {tmp_path / 'in.h5'}\n    packet_us: 7000\n"
            "  - use: hdf5_writer\n    path: copy.h5\n")
    run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path / "run")
    with h5py.File(tmp_path / "run" / "copy.h5") as f:
        t_offset = f["t_offset"][()]
        assert f["t_offset"].shape == () and t_offset == ev.t[0]  # the first packet's start
        g = f["events"]
        assert [g[c].dtype for c in ("x", "y", "t", "p")] == [np.uint16, np.uint16, np.int64,
                                                              np.uint8]
        assert np.array_equal(g["t"][:] + t_offset, ev.t)
        assert np.array_equal(g["p"][:], (ev.p > 0).astype(np.uint8))
        assert np.array_equal(g["x"][:], ev.x) and np.array_equal(g["y"][:], ev.y)
        assert g.attrs["width"] == 64
        ms_to_idx = f["ms_to_idx"][:]
        assert ms_to_idx.dtype == np.uint64
    rel = ev.t - ev.t[0]
    assert np.array_equal(ms_to_idx, np.searchsorted(rel, np.arange(len(ms_to_idx)) * 1000))
    assert same(read_hdf5(tmp_path / "run" / "copy.h5"), ev)


def dsec_get_events(f, t_start_us, t_end_us):
    """DSEC's documented slicing (its EventSlicer), re-implemented from the description: take
    t_offset off, widen the window to whole ms, look the ms up in ms_to_idx (None past its end),
    then cut the events inside at µs precision; times come back with t_offset added."""
    t_offset = int(f["t_offset"][()]) if "t_offset" in f else 0
    ms_to_idx = np.asarray(f["ms_to_idx"], np.int64)
    a, b = t_start_us - t_offset, t_end_us - t_offset
    ms0, ms1 = math.floor(a / 1000), math.ceil(b / 1000)
    if ms0 < 0 or ms1 >= len(ms_to_idx):
        return None
    i0, i1 = int(ms_to_idx[ms0]), int(ms_to_idx[ms1])
    t = np.asarray(f["events/t"][i0:i1], np.int64)
    k0, k1 = i0 + int(np.searchsorted(t, a, "left")), i0 + int(np.searchsorted(t, b, "left"))
    out = {c: np.asarray(f[f"events/{c}"][k0:k1]) for c in ("p", "x", "y")}
    out["t"] = np.asarray(f["events/t"][k0:k1], np.int64) + t_offset
    return out


def test_dsec_slicing_on_a_file_evchain_wrote(tmp_path):
    """ms_to_idx keeps DSEC's documented properties at every ms, and DSEC's slicing returns
    exactly the events of any window, up to the end of the stream."""
    g = Geometry(64, 48)
    rng = np.random.default_rng(5)
    # bursts on ms boundaries, equal times, a 7 ms gap, a stream not starting at 0
    t = np.sort(np.concatenate([rng.integers(0, 20_000, 3000), np.full(40, 5000),
                                np.full(30, 9999), rng.integers(27_000, 30_000, 500)]))
    t = t + 123_456_789
    n = len(t)
    ev = EventPacket(geometry=g, t_start=123_456_000, t_end=int(t[-1]) + 2500,
                     x=rng.integers(0, 64, n).astype(np.uint16),
                     y=rng.integers(0, 48, n).astype(np.uint16), t=t.astype(np.int64),
                     p=rng.choice(np.array([-1, 1], np.int8), n))
    w = Hdf5Writer()
    w.setup(Hdf5Writer.Params(path="e.h5"), make_context(g, None, tmp_path))
    run_filter(w, [ev.select(ev.t < 123_470_000).replace(t_end=123_470_000),
                   ev.select(ev.t >= 123_470_000).replace(t_start=123_470_000)])
    with h5py.File(tmp_path / "e.h5") as f:
        assert f["t_offset"][()] == ev.t_start
        rel = f["events/t"][:]
        ms_to_idx = f["ms_to_idx"][:].astype(np.int64)
        assert ms_to_idx[0] == 0
        for ms in range(1, len(ms_to_idx)):
            i = ms_to_idx[ms]
            assert i == n or rel[i] >= ms * 1000
            assert rel[i - 1] < ms * 1000
        assert len(ms_to_idx) == math.ceil((ev.t_end - ev.t_start) / 1000) + 1
        windows = [(ev.t_start, ev.t_end), (123_461_000, 123_461_001),
                   (123_461_500, 123_466_789), (123_476_000, 123_483_000),
                   (int(t[-1]), ev.t_end)] + [tuple(sorted(w)) for w in
                                             rng.integers(ev.t_start, ev.t_end, (40, 2))]
        for a, b in windows:
            if a == b:
                continue
            got = dsec_get_events(f, a, b)
            inside = (ev.t >= a) & (ev.t < b)
            assert got is not None, (a, b)
            assert np.array_equal(got["t"], ev.t[inside])
            assert np.array_equal(got["x"], ev.x[inside])
            assert np.array_equal(got["p"], (ev.p[inside] > 0).astype(np.uint8))
        assert dsec_get_events(f, ev.t_start, ev.t_end + 1000) is None  # past ms_to_idx


def test_reads_a_dsec_file_written_by_h5py_with_blosc(tmp_path):
    """DSEC's layout as its files have it: t uint32 after t_offset, p uint8, Blosc (zstd),
    ms_to_idx, no width/height attributes."""
    hdf5plugin = pytest.importorskip("hdf5plugin")
    rng = np.random.default_rng(3)
    n = 20_000
    t = np.sort(rng.integers(0, 2_000_000, n)).astype(np.uint32)
    x = rng.integers(0, 640, n).astype(np.uint16)
    y = rng.integers(0, 480, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.uint8)
    t_offset = 1_615_000_000_123_456
    blosc = hdf5plugin.Blosc(cname="zstd", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE)
    path = tmp_path / "events.h5"
    with h5py.File(path, "w") as f:
        for c, v in (("p", p), ("t", t), ("x", x), ("y", y)):
            f.create_dataset(f"events/{c}", data=v, chunks=(4096,), **blosc)
        f.create_dataset("ms_to_idx", data=np.searchsorted(
            t, np.arange(int(t[-1]) // 1000 + 2) * 1000).astype(np.uint64), **blosc)
        f.create_dataset("t_offset", data=np.int64(t_offset))
        assert f["events/t"].id.get_create_plist().get_filter(0)[0] == 32001  # Blosc
    with pytest.raises(DataError, match="no width/height.*640x480"):
        read_hdf5(path)
    ev = read_hdf5(path, width=640, height=480)
    assert np.array_equal(ev.t, t.astype(np.int64) + t_offset)
    assert np.array_equal(ev.p, np.where(p == 1, 1, -1)) and ev.p.dtype == np.int8
    assert np.array_equal(ev.x, x) and np.array_equal(ev.y, y)
    registry = make_registry()
    text = (f"chain:\n  - use: hdf5\n    path: {path}\n    width: 640\n    height: 480\n"
            "    packet_us: 50000\n  - use: hdf5_writer\n    path: copy.h5\n")
    run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path / "run")
    with h5py.File(tmp_path / "run" / "copy.h5") as f:
        assert f["events/t"].id.get_create_plist().get_filter(0)[0] == 32001  # the default
        assert f["t_offset"][()] == t_offset + int(t[0])
        assert np.array_equal(f["events/t"][:] + f["t_offset"][()], ev.t)


@pytest.mark.parametrize("compression, filter_id", [("gzip", 1), ("none", None)])
def test_write_compression(tmp_path, compression, filter_id):
    ev = random_events(3000, seed=6)
    path = write_hdf5(tmp_path / "e.h5", ev, compression=compression)
    with h5py.File(path) as f:
        plist = f["events/x"].id.get_create_plist()
        got = plist.get_filter(0)[0] if plist.get_nfilters() else None
        assert got == filter_id
    assert same(read_hdf5(path), ev)


def test_blosc_without_hdf5plugin_is_a_config_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "hdf5plugin", None)  # import fails as if not installed
    with pytest.raises(ConfigError, match="needs hdf5plugin.*compression: gzip"):
        Hdf5Writer().setup(Hdf5Writer.Params(path="e.h5"), make_context(None, None, tmp_path))


def test_earlier_files_with_plus_minus_one_still_read(tmp_path):
    ev = random_events(3000, seed=7)
    write_file(tmp_path / "old.h5", ev)  # int8 -1/+1, absolute t, no t_offset, no ms_to_idx
    assert same(read_hdf5(tmp_path / "old.h5"), ev)


@pytest.mark.parametrize("values, pattern", [
    ([1, 2, 0], r"events/p: event 1 has polarity 2; expected 0/1 \(DSEC: 0 OFF, 1 ON\) or -1/\+1"),
    ([-1, 1, 0], r"events/p holds both 0 and -1"),
    ([255, 1, 1], r"events/p: event 0 has polarity 255"),
])
def test_bad_polarity_names_the_field(tmp_path, values, pattern):
    ev = random_events(3, seed=8)
    write_file(tmp_path / "bad.h5", ev)
    with h5py.File(tmp_path / "bad.h5", "a") as f:
        del f["events/p"]
        f["events/p"] = np.array(values, np.int16 if min(values) < 0 else np.uint8)
    with pytest.raises(DataError, match=pattern):
        read_hdf5(tmp_path / "bad.h5")


def test_backward_time_names_the_event(tmp_path):
    ev = random_events(5, seed=9)
    write_file(tmp_path / "b.h5", ev.replace(t=np.array([1, 2, 3, 2, 5], np.int64)))
    with pytest.raises(DataError, match="events/t: event 3 goes back in time"):
        read_hdf5(tmp_path / "b.h5")


def test_failed_run_leaves_only_partial(tmp_path):
    ev = random_events(500, t_start=0, t_end=30_000, seed=2)
    write_file(tmp_path / "in.h5", ev)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "copy.h5").write_bytes(b"stale output of an earlier run")
    registry = make_registry(discover=False, plugins=(_FailPlugin(),))
    text = (f"chain:\n  - use: hdf5\n    path: {tmp_path / 'in.h5'}\n    packet_us: 7000\n"
            "  - use: hdf5_writer\n    path: copy.h5\n  - use: toy_fail\n")
    with pytest.raises(FilterError, match="disk on fire"):
        run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path / "run")
    assert not (tmp_path / "run" / "copy.h5").exists()
    assert (tmp_path / "run" / "copy.h5.partial").exists()


class _Fail(Filter):
    """Fails on the second packet."""

    name = "toy_fail"
    consumes = EventPacket

    def reset(self):
        self.seen = 0

    def process(self, packet):
        self.seen += 1
        if self.seen == 2:
            raise RuntimeError("disk on fire")
        return packet


class _FailPlugin:
    @hookimpl
    def evchain_filters(self):
        return [_Fail]


def test_source_contract_and_slices(tmp_path):
    ev = random_events(3000, t_start=100, t_end=50_000, seed=2)
    write_file(tmp_path / "in.h5", ev)
    packets = check_source(registry_cls("hdf5"), {"path": str(tmp_path / "in.h5"),
                                                  "packet_us": 5000}, out_dir=tmp_path,
                           max_packets=1000)
    whole = EventPacket.concat(packets)
    assert np.array_equal(whole.t, ev.t) and np.array_equal(whole.p, ev.p)


def registry_cls(name):
    return make_registry().get(name)


@pytest.mark.parametrize("mutate, pattern", [
    (lambda g: g.__delitem__("p"), "lacks datasets \\['p'\\]"),
    (lambda g: g.attrs.__delitem__("width"), "no width/height"),
    (lambda g: (g.__delitem__("x"), g.create_dataset("x", data=np.zeros((10, 2), np.uint16))),
     r"datasets events/x must be 1-D \(one value per event\), got shapes x \(10, 2\)"),
])
def test_bad_files(tmp_path, mutate, pattern):
    ev = random_events(10, seed=3)
    path = tmp_path / "bad.h5"
    write_file(path, ev)
    with h5py.File(path, "a") as f:
        mutate(f["events"])
    registry = make_registry()
    text = f"chain:\n  - use: hdf5\n    path: {path}\n"
    with pytest.raises(FilterError, match=f"{path}: .*{pattern}"):
        run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path / "r")


def test_not_hdf5_and_outside_sensor(tmp_path):
    (tmp_path / "x.h5").write_text("hello")
    registry = make_registry()
    with pytest.raises(FilterError, match="not an HDF5 file"):
        run_pipeline(pipeline_from_text(f"chain:\n  - use: hdf5\n    path: {tmp_path / 'x.h5'}\n",
                                        "p.yaml", registry), registry, tmp_path / "r")
    ev = random_events(10, seed=3)
    write_file(tmp_path / "small.h5", ev, width=8, height=8)
    with pytest.raises(FilterError, match="outside the 8x8 sensor"):
        run_pipeline(pipeline_from_text(
            f"chain:\n  - use: hdf5\n    path: {tmp_path / 'small.h5'}\n", "p.yaml", registry),
            registry, tmp_path / "r2")


def test_writer_takes_the_geometry_from_the_first_packet(tmp_path):
    ev = random_events(100, Geometry(40, 30), seed=10)
    w = Hdf5Writer()
    w.setup(Hdf5Writer.Params(path="e.h5", compression="none"), make_context(None, None, tmp_path))
    run_filter(w, [ev])
    back = read_hdf5(tmp_path / "e.h5")
    assert back.geometry == Geometry(40, 30) and same(back, ev)
