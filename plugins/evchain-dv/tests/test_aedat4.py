"""evchain-dv: AEDAT 4.0 round trips through dv-processing, the contract, and bad input."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

pytest.importorskip("dv_processing")

from evchain.bench import cut_every  # noqa: E402
from evchain.core.filter import Context  # noqa: E402
from evchain.core.packets import EventPacket, Geometry  # noqa: E402
from evchain.errors import ConfigError, DataError  # noqa: E402
from evchain.testing.synthetic import random_events  # noqa: E402

from evchain_dv.aedat4 import Aedat4Source, Aedat4Writer  # noqa: E402
from evchain_dv.bench import write_file  # noqa: E402

GEOMETRY = Geometry(346, 260)


def stream(n=3000, seed=1, t_start=1_700_000_000_000_000, span=300_000) -> list[EventPacket]:
    ev = random_events(n, GEOMETRY, t_start=t_start, t_end=t_start + span, seed=seed)
    return cut_every(ev, 7_000)


def read_all(path: Path, **params) -> tuple[EventPacket, Context]:
    src = Aedat4Source()
    src.id = "aedat4"
    ctx = Context(out_dir=path.parent)
    src.setup(Aedat4Source.Params(path=str(path), **params), ctx)
    try:
        packets = list(src.packets())
    finally:
        src.close()
    return EventPacket.concat(packets) if packets else None, ctx


def assert_same_events(got: EventPacket, packets: list[EventPacket]) -> None:
    want = EventPacket.concat(packets)
    assert len(got) == len(want)
    for c in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(got, c), getattr(want, c), err_msg=c)
        assert getattr(got, c).dtype == getattr(want, c).dtype


def test_round_trip_identical_events(tmp_path, filter_contract):
    packets = stream()
    path = write_file(tmp_path / "rt.aedat4", packets)
    got, ctx = read_all(path)
    assert ctx.geometry == GEOMETRY  # from the event stream's resolution
    assert_same_events(got, packets)
    assert got.t_start == packets[0].t[0] and got.t_end == packets[-1].t[-1] + 1
    # the source contract: valid, consecutive slices; reset() and replay give the same
    first = filter_contract.check_source(Aedat4Source, {"path": str(path), "packet_us": 10_000})
    assert all(p.t_end - p.t_start <= 10_000 for p in first)
    assert_same_events(EventPacket.concat(first), packets)


def test_every_compression_round_trips(tmp_path):
    packets = stream(n=500, seed=2)
    for compression in ("none", "lz4_high", "zstd"):
        path = write_file(tmp_path / f"{compression}.aedat4", packets, compression=compression)
        assert_same_events(read_all(path)[0], packets)


def test_writer_contract_and_output(tmp_path, filter_contract):
    packets = stream(n=1200, seed=3)
    out = filter_contract.check_filter(Aedat4Writer, {"path": "w.aedat4"}, packets)
    np.testing.assert_array_equal(out["t"], EventPacket.concat(packets).t)  # passed through
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["w.aedat4"], files  # no .partial left, no stray files
    assert_same_events(read_all(tmp_path / "w.aedat4")[0], packets)


def test_same_timestamp_across_packets_and_time_gaps(tmp_path):
    g = GEOMETRY
    t = np.array([5, 5, 5, 5, 90_000, 90_000, 400_000], np.int64)
    ev = EventPacket(geometry=g, t_start=0, t_end=400_001, x=np.arange(7, dtype=np.uint16),
                     y=np.arange(7, dtype=np.uint16), t=t,
                     p=np.array([1, -1, 1, -1, 1, 1, -1], np.int8))
    path = write_file(tmp_path / "gap.aedat4", [ev.select(slice(0, 2)), ev.select(slice(2, 7))])
    src = Aedat4Source()
    src.setup(Aedat4Source.Params(path=str(path), packet_us=1000), Context(out_dir=tmp_path))
    packets = list(src.packets())
    src.close()
    assert packets[0].t_start == 5 and packets[-1].t_end == 400_001
    assert all(a.t_end == b.t_start for a, b in zip(packets, packets[1:], strict=False))
    assert_same_events(EventPacket.concat(packets), [ev])


def test_no_events_gives_a_readable_file(tmp_path):
    w = Aedat4Writer()
    w.setup(Aedat4Writer.Params(path="empty.aedat4"),
            Context(out_dir=tmp_path, geometry=Geometry(64, 48)))
    w.process(EventPacket.empty(Geometry(64, 48), 0, 1000))
    w.flush()
    w.close()
    got, ctx = read_all(tmp_path / "empty.aedat4")
    assert got is None and ctx.geometry == Geometry(64, 48)


@pytest.mark.parametrize("buffer_events", [0, 1_000_000])
def test_failed_run_leaves_only_partial(tmp_path, buffer_events):
    (tmp_path / "run.aedat4").write_bytes(b"stale output of an earlier run")
    w = Aedat4Writer()
    w.setup(Aedat4Writer.Params(path="run.aedat4", buffer_events=buffer_events),
            Context(out_dir=tmp_path))
    for p in stream(n=300)[:3]:
        w.process(p)
    w.close()  # no flush: the run failed
    assert not (tmp_path / "run.aedat4").exists()
    # the partial file exists once the writer has opened it (buffer full)
    assert (tmp_path / "run.aedat4.partial").exists() == (buffer_events == 0)


@pytest.mark.parametrize("buffer_events", [0, 100, 10**9])
def test_buffering_does_not_change_the_file(tmp_path, buffer_events):
    packets = stream(n=1000, seed=4)
    path = write_file(tmp_path / f"b{buffer_events}.aedat4", packets,
                      buffer_events=buffer_events)
    assert_same_events(read_all(path)[0], packets)


def test_writer_needs_aedat4_name(tmp_path):
    with pytest.raises(ValidationError, match="must end in '.aedat4'"):
        Aedat4Writer.Params(path="out.aedat4.bak")
    # and in a pipeline file it is a ConfigError naming the file, before anything runs
    import evchain

    yaml = tmp_path / "bad.yaml"
    yaml.write_text("name: bad\nseed: 0\nchain:\n  - use: aedat4\n    path: in.aedat4\n"
                    "  - use: aedat4_writer\n    path: out.bin\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*must end in '\.aedat4'"):
        evchain.run(yaml, out_dir=tmp_path / "out")
    with pytest.raises(ValidationError, match="compression"):
        Aedat4Writer.Params(compression="gzip")


def _open(path, **params):
    src = Aedat4Source()
    src.setup(Aedat4Source.Params(path=str(path), **params), Context(out_dir=Path(path).parent))
    try:
        return list(src.packets())
    finally:
        src.close()


def test_bad_input_names_the_file(tmp_path):
    with pytest.raises(DataError, match=r"missing\.aedat4: file not found"):
        _open(tmp_path / "missing.aedat4")
    with pytest.raises(DataError, match="not a file"):
        _open(tmp_path)
    text = tmp_path / "notes.aedat4"
    text.write_text("hello\n")
    with pytest.raises(DataError, match=r"notes\.aedat4: not an AEDAT 4.0 file"):
        _open(text)
    old = tmp_path / "old.aedat4"
    old.write_bytes(b"#!AER-DAT2.0\r\n# This is a raw AE data file\r\n")
    with pytest.raises(DataError, match="use the 'aedat' source"):
        _open(old)
    good = write_file(tmp_path / "good.aedat4", stream(n=2000))
    data = good.read_bytes()
    for name, cut in (("head.aedat4", 20), ("cut.aedat4", len(data) * 6 // 10)):
        (tmp_path / name).write_bytes(data[:cut])
        with pytest.raises(DataError) as info:
            _open(tmp_path / name)
        msg = str(info.value)
        assert msg.startswith(str(tmp_path / name)) and "Stacktrace" not in msg, msg
    with pytest.raises(DataError, match=r"good\.aedat4: no event stream 'frames'.*'events'"):
        _open(good, stream="frames")


def test_a_packet_dv_cannot_decode_names_file_stream_and_count(tmp_path):
    """A batch that dv-processing fails to decode (its RuntimeError) is a DataError naming the
    file, the stream and the events or IMU samples read before it, without DV's stack trace."""
    good = write_file(tmp_path / "good.aedat4", stream(n=500))
    src = Aedat4Source()
    src.setup(Aedat4Source.Params(path=str(good)), Context(out_dir=tmp_path))

    class Broken:  # DV's recording, every batch failing to decode
        def __init__(self, recording):
            self.recording = recording

        def __getattr__(self, name):
            return getattr(self.recording, name)

        def getNextEventBatch(self, stream):  # noqa: N802 (DV's name)
            raise RuntimeError("decompression failed\nStacktrace:\n  0# dv::io::Reader")

        getNextImuBatch = getNextEventBatch

    real = src.recording
    src.recording = Broken(real)
    try:
        with pytest.raises(DataError, match=r"good\.aedat4: after event 0: cannot decode the "
                           r"next packet of stream 'events': decompression failed$"):
            list(src.packets())
        src.imu_stream = "imu"
        with pytest.raises(DataError, match=r"good\.aedat4: after IMU sample 0: cannot decode "
                           r"the next packet of stream 'imu': decompression failed$"):
            list(src._imu_batches())
    finally:
        src.recording = real
        src.close()


def test_pipeline_through_the_registry(tmp_path):
    """The plugin is found through its entry point and runs from YAML."""
    import evchain
    from evchain.core.registry import make_registry

    info = make_registry().filters
    assert info["aedat4"].distribution == "evchain-dv"
    assert info["aedat4_writer"].distribution == "evchain-dv"
    packets = stream(n=800, seed=5)
    src = write_file(tmp_path / "in.aedat4", packets)
    yaml = tmp_path / "copy.yaml"
    yaml.write_text(textwrap.dedent(f"""\
        name: aedat4-copy
        seed: 0
        chain:
          - use: aedat4
            path: {src}
            packet_us: 5000
          - use: aedat4_writer
            path: copy.aedat4
        """))
    evchain.run(yaml, out_dir=tmp_path / "out")
    assert_same_events(read_all(tmp_path / "out" / "copy.aedat4")[0], packets)


def _dv_events(t, x, y, polarity):
    a = np.zeros(len(t), [("timestamp", "<i8"), ("x", "<i2"), ("y", "<i2"), ("polarity", "i1")])
    a["timestamp"], a["x"], a["y"], a["polarity"] = t, x, y, polarity
    return a


def test_event_columns_convert_and_check():
    """dv-processing's event arrays (file and network sources) to evchain columns."""
    from evchain_dv.aedat4 import event_columns

    g = Geometry(10, 8)
    cols = event_columns(_dv_events([1, 1, 2], [0, 9, 3], [7, 0, 1], [1, 0, 1]), g, "w", 0, None)
    assert cols["p"].tolist() == [1, -1, 1] and cols["p"].dtype == np.int8
    assert cols["x"].tolist() == [0, 9, 3] and cols["x"].dtype == np.uint16
    assert cols["t"].dtype == np.int64
    with pytest.raises(DataError, match="w: event 2: timestamp goes backwards"):
        event_columns(_dv_events([1, 3, 2], [0] * 3, [0] * 3, [1] * 3), g, "w", 0, None)
    with pytest.raises(DataError, match="w: event 5: timestamp goes backwards"):
        event_columns(_dv_events([1, 3], [0] * 2, [0] * 2, [1] * 2), g, "w", 5, 2)
    with pytest.raises(DataError, match=r"w: event 1 at \(-1, 0\) outside the 10x8 sensor"):
        event_columns(_dv_events([1, 3], [0, -1], [0, 0], [1, 1]), g, "w", 0, None)
    with pytest.raises(DataError, match=r"w: event 4 at \(0, 8\) outside"):
        event_columns(_dv_events([1, 3], [0, 0], [0, 8], [1, 1]), g, "w", 3, None)


# -- IMU samples -------------------------------------------------------------------------------

def imu_samples(t0: int, t1: int, every_us: int = 1000, seed: int = 5) -> np.ndarray:
    """IMU series entries at ``every_us`` in [t0, t1), values exact in float32 (as DV stores
    them)."""
    from evchain.core.series import IMU

    rng = np.random.default_rng(seed)
    t = np.arange(t0, t1, every_us, dtype=np.int64)
    v = rng.normal(0, 1, (len(t), 7)) * [1, 1, 1, 50, 50, 50, 3] + [0, 0, 0, 0, 0, 0, 30]
    v = v.astype(np.float32).astype(np.float64)
    return IMU.array(t=t, ax=v[:, 0], ay=v[:, 1], az=v[:, 2], gx=v[:, 3], gy=v[:, 4],
                     gz=v[:, 5], temperature_c=v[:, 6])


def with_imu(packets: list[EventPacket], imu: np.ndarray) -> list[EventPacket]:
    from evchain.testing.contract import recut

    whole = EventPacket.concat(packets).with_series("imu", imu)
    return recut([whole], [p.t_start for p in packets[1:]])


def dv_file(path: Path, imu_rows=(), stream_name="imu", events=True) -> Path:
    """An AEDAT 4.0 file written with dv-processing as DV writes one: events of a 346x260
    sensor and IMU samples ``(t, temperature, ax, ay, az, gx, gy, gz)`` in the chip's axes."""
    import dv_processing as dv

    config = dv.io.MonoCameraWriter.Config("DAVIS346_test")
    config.addEventStream((346, 260))
    if stream_name is not None:
        config.addImuStream(stream_name)
    writer = dv.io.MonoCameraWriter(str(path), config)
    if events:
        store = dv.EventStore()
        for t in range(1_000, 100_000, 1_000):
            store.push_back(t, 10, 20, True)
        writer.writeEvents(store)
    for r in imu_rows:
        writer.writeImu(dv.IMU(*r, 0.0, 0.0, 0.0), stream_name)
    del writer
    return path


def test_imu_round_trip(tmp_path):
    packets = stream(n=2000, seed=6)
    events = EventPacket.concat(packets)
    imu = imu_samples(int(events.t[0]), int(events.t[-1]) + 1)   # the source's span
    path = write_file(tmp_path / "imu.aedat4", with_imu(packets, imu))
    got, ctx = read_all(path)
    assert_same_events(got, packets)
    np.testing.assert_array_equal(got.series["imu"], imu)   # every field, bit for bit
    m = ctx.metrics["aedat4"]
    assert m["imu_stream"] == "imu" and m["imu_samples"] == len(imu)
    assert m["imu_before_events"] == 0 and m["imu_after_events"] == 0


def test_imu_packets_carry_their_slice(tmp_path, filter_contract):
    packets = stream(n=1500, seed=7)
    events = EventPacket.concat(packets)
    imu = imu_samples(int(events.t[0]), int(events.t[-1]) + 1, every_us=700)
    path = write_file(tmp_path / "s.aedat4", with_imu(packets, imu))
    out = filter_contract.check_source(Aedat4Source, {"path": str(path), "packet_us": 10_000})
    for p in out:
        s = p.series["imu"]
        assert np.all((s["t"] >= p.t_start) & (s["t"] < p.t_end))
    np.testing.assert_array_equal(np.concatenate([p.series["imu"] for p in out]), imu)


def test_imu_axes_and_units_of_a_dv_file(tmp_path):
    """DV's chip axes (libcaer's) become the camera's: x and z negated, g and deg/s kept."""
    path = dv_file(tmp_path / "dv.aedat4", [(5_000, 31.5, 0.25, -1.0, 0.125, 10.0, 5.0, 3.0)])
    got, ctx = read_all(path)
    s = got.series["imu"]
    assert len(s) == 1 and s["t"][0] == 5_000
    assert (s["ax"][0], s["ay"][0], s["az"][0]) == (-0.25, -1.0, -0.125)
    assert (s["gx"][0], s["gy"][0], s["gz"][0]) == (-10.0, 5.0, -3.0)
    assert s["temperature_c"][0] == 31.5


def test_imu_outside_the_events_is_counted(tmp_path):
    rows = [(t, 30.0, 0.0, -1.0, 0.0, 1.0, 2.0, 3.0) for t in (500, 50_000, 200_000, 300_000)]
    got, ctx = read_all(dv_file(tmp_path / "o.aedat4", rows))
    m = ctx.metrics["aedat4"]
    assert list(got.series["imu"]["t"]) == [50_000]
    assert (m["imu_before_events"], m["imu_samples"], m["imu_after_events"]) == (1, 1, 2)


def test_imu_bad_input_names_the_file_and_field(tmp_path):
    # no IMU stream: no series, unless one is asked for by name
    plain = dv_file(tmp_path / "plain.aedat4", stream_name=None)
    got, ctx = read_all(plain)
    assert "imu" not in got.series and ctx.metrics["aedat4"]["imu_stream"] is None
    with pytest.raises(DataError, match=r"plain\.aedat4: no IMU stream 'imu'; IMU streams: "
                                        r"none, all streams: \['events'\]"):
        read_all(plain, imu_stream="imu")
    with pytest.raises(DataError, match=r"plain\.aedat4: stream 'events' is not an IMU stream"):
        read_all(plain, imu_stream="events")
    # a reading that is not a number
    nan = dv_file(tmp_path / "nan.aedat4", [(2_000, 30.0, 0.0, -1.0, 0.0, 1.0, 2.0, 3.0),
                                            (3_000, 30.0, 0.0, -1.0, 0.0, 1.0, float("nan"),
                                             3.0)])
    with pytest.raises(DataError, match=r"nan\.aedat4: stream 'imu': IMU sample 1: field "
                                        r"gyroscopeY is nan; expected a finite reading"):
        read_all(nan)
    # imu: false ignores the stream
    got, _ = read_all(nan, imu=False)
    assert "imu" not in got.series


def test_writer_refuses_imu_that_starts_after_the_file_was_opened(tmp_path):
    packets = stream(n=600, seed=8)
    late = with_imu(packets[2:], imu_samples(packets[2].t_start, packets[-1].t_end))
    w = Aedat4Writer()
    w.id = "aedat4_writer"
    w.setup(Aedat4Writer.Params(path="late.aedat4", buffer_events=0), Context(out_dir=tmp_path))
    for p in packets[:2]:
        w.process(p)
    with pytest.raises(DataError, match="carries IMU samples, but the file was opened without "
                                        "an IMU stream"):
        w.process(late[0])
    w.close()
