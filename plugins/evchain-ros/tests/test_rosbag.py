"""evchain-ros: the EventArray codec against rosbags, bag round trips, the contract, bad input."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from evchain.bench import cut_every  # noqa: E402
from evchain.core.filter import Context  # noqa: E402
from evchain.core.packets import EventPacket, Geometry  # noqa: E402
from evchain.errors import DataError  # noqa: E402
from evchain.testing.synthetic import random_events  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402

from evchain_ros.bench import write_bag  # noqa: E402
from evchain_ros.msgs import EVENT_ARRAY, ROS1_MD5, decode, encode, typestore  # noqa: E402
from evchain_ros.rosbag import RosbagSource, RosbagWriter  # noqa: E402

GEOMETRY = Geometry(240, 180)
T0 = 1_700_000_000_123_456  # absolute µs, as ROS (Unix) time gives them


def stream(n=3000, seed=1, t_start=T0, span=300_000) -> list[EventPacket]:
    ev = random_events(n, GEOMETRY, t_start=t_start, t_end=t_start + span, seed=seed)
    return cut_every(ev, 7_000)


def read_all(path: Path, **params) -> tuple[EventPacket | None, Context]:
    src = RosbagSource()
    src.id = "rosbag"
    ctx = Context(out_dir=Path(path).parent)
    src.setup(RosbagSource.Params(path=str(path), **params), ctx)
    try:
        packets = list(src.packets())
    finally:
        src.close()
    return (EventPacket.concat(packets) if packets else None), ctx


def assert_same_events(got: EventPacket, packets: list[EventPacket]) -> None:
    want = EventPacket.concat(packets)
    assert len(got) == len(want)
    for c in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(got, c), getattr(want, c), err_msg=c)
        assert getattr(got, c).dtype == getattr(want, c).dtype


def _rosbags_message(store, x, y, t_ns, p, frame_id, ros2):
    T, H, EA, Ev = (store.types[k] for k in ("builtin_interfaces/msg/Time",
                                             "std_msgs/msg/Header", EVENT_ARRAY,
                                             "dvs_msgs/msg/Event"))
    events = [Ev(x=int(a), y=int(b), ts=T(sec=int(c) // 10**9, nanosec=int(c) % 10**9),
                 polarity=bool(d > 0)) for a, b, c, d in zip(x, y, t_ns, p, strict=True)]
    stamp = T(sec=17, nanosec=5000)
    header = H(stamp=stamp, frame_id=frame_id) if ros2 else H(seq=3, stamp=stamp,
                                                              frame_id=frame_id)
    return EA(header=header, height=180, width=240, events=events)


@pytest.mark.parametrize("ros2", [False, True])
def test_codec_matches_rosbags_byte_for_byte(ros2):
    store, rng = typestore(ros2), np.random.default_rng(7)
    for n in (0, 1, 2, 3, 4, 57):
        for frame_id in ("", "a", "ab", "abc", "davis"):  # every string padding in CDR
            x = rng.integers(0, 240, n).astype(np.uint16)
            y = rng.integers(0, 180, n).astype(np.uint16)
            t = np.sort(rng.integers(T0, T0 + 10**7, n)).astype(np.int64)
            p = rng.choice(np.array([-1, 1], np.int8), n)
            msg = _rosbags_message(store, x, y, t * 1000, p, frame_id, ros2)
            ref = bytes(store.serialize_cdr(msg, EVENT_ARRAY) if ros2
                        else store.serialize_ros1(msg, EVENT_ARRAY))
            ours = encode(x, y, t, p, height=180, width=240, seq=3, stamp_us=17_000_005,
                          frame_id=frame_id, ros2=ros2)
            assert ours == ref, (n, frame_id)
            h, w, cols = decode(ref, ros2)
            assert (h, w) == (180, 240)
            for k, v in {"x": x, "y": y, "t": t, "p": p}.items():
                np.testing.assert_array_equal(cols[k], v, err_msg=k)


def test_ros1_type_hash_is_rpg_dvs_ros():
    assert typestore(False).generate_msgdef(EVENT_ARRAY)[1] == ROS1_MD5


def test_other_eventarray_layout_is_refused(tmp_path):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)  # same type name, fields in another order
    store.register({**get_types_from_msg("uint16 x\nuint16 y\ntime ts\nbool polarity\n",
                                         "dvs_msgs/msg/Event"),
                    **get_types_from_msg("Header header\ndvs_msgs/Event[] events\n"
                                         "uint32 height\nuint32 width\n", EVENT_ARRAY)})
    T, H, EA = (store.types[k] for k in ("builtin_interfaces/msg/Time", "std_msgs/msg/Header",
                                         EVENT_ARRAY))
    msg = EA(header=H(seq=0, stamp=T(sec=1, nanosec=0), frame_id=""), events=[], height=1,
             width=1)
    w = Writer1(tmp_path / "other.bag")
    w.open()
    conn = w.add_connection("/dvs/events", EVENT_ARRAY, typestore=store)
    w.write(conn, 1, store.serialize_ros1(msg, EVENT_ARRAY))
    w.close()
    with pytest.raises(DataError, match=r"other\.bag: topic '/dvs/events': "
                                        r"dvs_msgs/msg/EventArray with MD5 \w+, a layout other"):
        read_all(tmp_path / "other.bag")


@pytest.mark.parametrize("ros2", [False, True])
def test_decode_truncates_sub_microsecond_parts(ros2):
    store = typestore(ros2)
    t_ns = np.array([T0 * 1000 + 999, T0 * 1000 + 1000, T0 * 1000 + 1999], np.int64)
    msg = _rosbags_message(store, [1, 2, 3], [4, 5, 6], t_ns, [1, -1, 1], "f", ros2)
    raw = store.serialize_cdr(msg, EVENT_ARRAY) if ros2 else store.serialize_ros1(msg,
                                                                                  EVENT_ARRAY)
    _, _, cols = decode(raw, ros2)
    np.testing.assert_array_equal(cols["t"], [T0, T0 + 1, T0 + 1])


@pytest.mark.parametrize("fmt,storage,compression", [
    ("ros1", "sqlite3", "none"), ("ros1", "sqlite3", "lz4"), ("ros1", "sqlite3", "bz2"),
    ("ros2", "sqlite3", "none"), ("ros2", "mcap", "none")])
def test_round_trip_identical_events(tmp_path, filter_contract, fmt, storage, compression):
    packets = stream()
    path = write_bag(tmp_path / ("rt.bag" if fmt == "ros1" else "rt"), packets, format=fmt,
                     storage=storage, compression=compression)
    if compression != "none":
        assert f"compression={compression}".encode() in path.read_bytes()
    if fmt == "ros2":
        assert (path / f"rt.{'db3' if storage == 'sqlite3' else 'mcap'}").is_file()
    assert path.is_file() if fmt == "ros1" else (path / "metadata.yaml").is_file()
    got, ctx = read_all(path)
    assert ctx.geometry == GEOMETRY  # from the messages' width/height
    assert_same_events(got, packets)
    assert got.t_start == packets[0].t[0] and got.t_end == packets[-1].t[-1] + 1  # absolute
    first = filter_contract.check_source(RosbagSource, {"path": str(path), "packet_us": 10_000})
    assert all(p.t_end - p.t_start <= 10_000 for p in first)
    assert_same_events(EventPacket.concat(first), packets)
    # rosbags' own generic deserialiser reads what we wrote, message by message
    with AnyReader([path], default_typestore=typestore(True)) as reader:
        conns = [c for c in reader.connections if c.topic == "/dvs/events"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    assert len(msgs) == sum(1 for p in packets if len(p))  # one message per non-empty packet
    assert msgs[0].width == 240 and msgs[0].height == 180 and msgs[0].header.frame_id == "dvs"
    ev = msgs[1].events[0]
    want = EventPacket.concat([p for p in packets if len(p)][1:2])
    assert (ev.x, ev.y, ev.polarity) == (want.x[0], want.y[0], want.p[0] > 0)
    assert ev.ts.sec * 10**6 + ev.ts.nanosec // 1000 == want.t[0]


def test_writer_contract_and_output(tmp_path, filter_contract):
    packets = stream(n=1200, seed=3)
    out = filter_contract.check_filter(RosbagWriter, {"path": "w.bag"}, packets)
    np.testing.assert_array_equal(out["t"], EventPacket.concat(packets).t)  # passed through
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.bag"]  # no .partial left
    assert_same_events(read_all(tmp_path / "w.bag")[0], packets)


def test_other_topic_and_repeated_times(tmp_path):
    t = np.array([T0, T0, T0, T0 + 5, T0 + 90_000, T0 + 90_000], np.int64)
    ev = EventPacket(geometry=GEOMETRY, t_start=T0, t_end=T0 + 90_001,
                     x=np.arange(6, dtype=np.uint16), y=np.arange(6, dtype=np.uint16), t=t,
                     p=np.array([1, -1, 1, -1, 1, 1], np.int8))
    parts = [ev.select(slice(0, 2)).replace(t_end=T0 + 1),
             ev.select(slice(2, 6)).replace(t_start=T0 + 1)]
    path = write_bag(tmp_path / "cam.bag", parts, topic="/cam0/events")
    got, _ = read_all(path, topic="/cam0/events", packet_us=1000)
    assert_same_events(got, [ev])


def test_failed_run_leaves_only_partial(tmp_path):
    for fmt, name in (("ros1", "run.bag"), ("ros2", "run2")):
        stale = tmp_path / name
        stale.write_bytes(b"stale output of an earlier run")
        w = RosbagWriter()
        w.setup(RosbagWriter.Params(path=name, format=fmt), Context(out_dir=tmp_path))
        for p in stream(n=300)[:3]:
            w.process(p)
        w.close()  # no flush: the run failed
        assert not stale.exists()
        assert (tmp_path / f"{name}.partial").exists()


def test_writer_refuses_what_ros_cannot_hold(tmp_path):
    w = RosbagWriter()
    w.setup(RosbagWriter.Params(path="neg.bag"), Context(out_dir=tmp_path))
    with pytest.raises(DataError, match=r"neg\.bag: event times -5\.\.-5 us do not fit ROS time"):
        w.process(random_events(1, GEOMETRY, t_start=-5, t_end=-4))
    w.close()
    (tmp_path / "notabag").mkdir()
    (tmp_path / "notabag" / "keep.txt").write_text("user data")
    with pytest.raises(DataError, match="not a ROS 2 bag; not replacing it"):
        write_bag(tmp_path / "notabag", stream(n=50), format="ros2")
    assert (tmp_path / "notabag" / "keep.txt").exists()


def _bag_with(path: Path, msgtype: str, raws: list[bytes], topic="/dvs/events") -> Path:
    store = typestore(False)
    if msgtype != EVENT_ARRAY:
        from rosbags.typesys import Stores, get_typestore
        store = get_typestore(Stores.ROS1_NOETIC)
    w = Writer1(path)
    w.open()
    conn = w.add_connection(topic, msgtype, typestore=store)
    for i, raw in enumerate(raws):
        w.write(conn, 1000 + i, raw)
    w.close()
    return path


def _msg(x, y, t, p, width=240, height=180):
    return encode(np.array(x, np.uint16), np.array(y, np.uint16), np.array(t, np.int64),
                  np.array(p, np.int8), height=height, width=width, seq=0, stamp_us=T0,
                  frame_id="dvs", ros2=False)


def test_bad_input_names_the_file(tmp_path):
    with pytest.raises(DataError, match=r"missing\.bag: not found"):
        read_all(tmp_path / "missing.bag")
    text = tmp_path / "notes.bag"
    text.write_text("hello, not a bag\n")
    with pytest.raises(DataError, match=r"notes\.bag: not a readable ROS bag"):
        read_all(text)
    empty_dir = tmp_path / "folder"
    empty_dir.mkdir()
    with pytest.raises(DataError, match=r"folder: not a readable ROS bag"):
        read_all(empty_dir)
    good = write_bag(tmp_path / "good.bag", stream(n=200))
    with pytest.raises(DataError, match=r"good\.bag: no topic '/events'; topics: /dvs/events "
                                        r"\(dvs_msgs/msg/EventArray\)"):
        read_all(good, topic="/events")
    store = typestore(False)
    string = store.serialize_ros1(store.types["std_msgs/msg/String"](data="hi"),
                                  "std_msgs/msg/String")
    wrong = _bag_with(tmp_path / "wrong.bag", "std_msgs/msg/String", [bytes(string)])
    with pytest.raises(DataError, match=r"wrong\.bag: topic '/dvs/events' has type "
                                        r"std_msgs/msg/String; expected dvs_msgs/msg/EventArray"):
        read_all(wrong)
    ok = _msg([1, 2], [3, 4], [T0, T0 + 1], [1, -1])
    cut = _bag_with(tmp_path / "cut.bag", EVENT_ARRAY, [ok, ok[:-5]])
    with pytest.raises(DataError, match=r"cut\.bag: topic '/dvs/events' message 1: not a "
                                        r"dvs_msgs/msg/EventArray \(.*bytes, expected"):
        read_all(cut)
    back = _bag_with(tmp_path / "back.bag", EVENT_ARRAY,
                     [ok, _msg([1, 2], [3, 4], [T0 + 1, T0 - 7], [1, 1])])
    with pytest.raises(DataError, match=r"back\.bag: topic '/dvs/events' message 1 event 1 "
                                        r"\(event 3 of the topic\): timestamp goes backwards"):
        read_all(back)
    outside = _bag_with(tmp_path / "outside.bag", EVENT_ARRAY,
                        [_msg([5, 300], [3, 4], [T0, T0 + 1], [1, 1])])
    with pytest.raises(DataError, match=r"outside\.bag: .* event 1 at \(300, 4\) outside the "
                                        r"240x180 sensor"):
        read_all(outside)
    nosize = _bag_with(tmp_path / "nosize.bag", EVENT_ARRAY, [_msg([1], [1], [T0], [1], 0, 0)])
    with pytest.raises(DataError, match=r"nosize\.bag: .*give the parameters width and height"):
        read_all(nosize)
    got, ctx = read_all(nosize, width=10, height=10)
    assert ctx.geometry == Geometry(10, 10) and len(got) == 1


def test_pipeline_through_the_registry(tmp_path):
    """The plugin is found through its entry point and runs from YAML, ROS 1 in, ROS 2 out."""
    import evchain
    from evchain.core.registry import make_registry

    info = make_registry().filters
    assert info["rosbag"].distribution == "evchain-ros"
    assert info["rosbag_writer"].distribution == "evchain-ros"
    packets = stream(n=800, seed=5)
    src = write_bag(tmp_path / "in.bag", packets)
    yaml = tmp_path / "copy.yaml"
    yaml.write_text(textwrap.dedent(f"""\
        name: rosbag-copy
        seed: 0
        chain:
          - use: rosbag
            path: {src}
            packet_us: 5000
          - use: rosbag_writer
            path: copy
            format: ros2
        """))
    evchain.run(yaml, out_dir=tmp_path / "out")
    assert_same_events(read_all(tmp_path / "out" / "copy")[0], packets)


# -- IMU samples (sensor_msgs/Imu) -----------------------------------------------------------

def imu_samples(t0: int, t1: int, every_us: int = 1000, seed: int = 5) -> np.ndarray:
    from evchain.core.series import IMU

    rng = np.random.default_rng(seed)
    t = np.arange(t0, t1, every_us, dtype=np.int64)
    v = rng.normal(0, 1, (len(t), 6)) * [1, 1, 1, 50, 50, 50]
    return IMU.array(t=t, ax=v[:, 0], ay=v[:, 1], az=v[:, 2], gx=v[:, 3], gy=v[:, 4],
                     gz=v[:, 5], temperature_c=np.nan)


def with_imu(packets: list[EventPacket], imu: np.ndarray) -> list[EventPacket]:
    from evchain.testing.contract import recut

    whole = EventPacket.concat(packets).with_series("imu", imu)
    return recut([whole], [p.t_start for p in packets[1:]])


def _imu_msg(t_us, gyro_rad_s, accel_ms2, gyro_cov0=0.0, accel_cov0=0.0, store=None):
    store = store or typestore(False)
    T, H, Q, V, M = (store.types[k] for k in (
        "builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Quaternion",
        "geometry_msgs/msg/Vector3", "sensor_msgs/msg/Imu"))
    cov = np.zeros(9)
    msg = M(header=H(seq=0, stamp=T(sec=t_us // 10**6, nanosec=t_us % 10**6 * 1000),
                     frame_id="base_link"),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
            angular_velocity=V(*map(float, gyro_rad_s)),
            angular_velocity_covariance=np.r_[gyro_cov0, np.zeros(8)],
            linear_acceleration=V(*map(float, accel_ms2)),
            linear_acceleration_covariance=np.r_[accel_cov0, np.zeros(8)])
    return bytes(store.serialize_ros1(msg, "sensor_msgs/msg/Imu"))


def _bag_with_imu(path: Path, imu_raws: list[bytes], imu_topics=("/dvs/imu",),
                  imu_type="sensor_msgs/msg/Imu", imu_store=None) -> Path:
    """A ROS 1 bag as rpg_dvs_ros records one: events on /dvs/events, IMU messages."""
    w = Writer1(path)
    w.open()
    ev = w.add_connection("/dvs/events", EVENT_ARRAY, typestore=typestore(False))
    w.write(ev, 1, _msg([1, 2, 3], [3, 4, 5], [T0, T0 + 50_000, T0 + 99_999], [1, -1, 1]))
    for topic in imu_topics:
        conn = w.add_connection(topic, imu_type, typestore=imu_store or typestore(False))
        for i, raw in enumerate(imu_raws):
            w.write(conn, 2 + i, raw)
    w.close()
    return path


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_imu_round_trip(tmp_path, fmt):
    packets = stream(n=1500, seed=9)
    events = EventPacket.concat(packets)
    imu = imu_samples(int(events.t[0]), int(events.t[-1]) + 1)
    path = write_bag(tmp_path / ("imu.bag" if fmt == "ros1" else "imu"),
                     with_imu(packets, imu), format=fmt)
    got, ctx = read_all(path)
    assert_same_events(got, packets)
    s = got.series["imu"]
    np.testing.assert_array_equal(s["t"], imu["t"])
    for c in ("ax", "ay", "az", "gx", "gy", "gz"):   # via rad/s and m/s²: within rounding
        np.testing.assert_allclose(s[c], imu[c], rtol=1e-12, atol=1e-12, err_msg=c)
    assert np.isnan(s["temperature_c"]).all()          # sensor_msgs/Imu has none
    m = ctx.metrics["rosbag"]
    assert (m["imu_topic"], m["imu_samples"]) == ("/dvs/imu", len(imu))


def test_imu_units_of_a_driver_bag(tmp_path):
    """rad/s become deg/s, m/s² g; the axes (camera frame, as rpg_dvs_ros publishes) stay."""
    raws = [_imu_msg(T0 + 10_000, (0.1, -0.2, 0.3), (0.0, -9.80665, 4.903325)),
            _imu_msg(T0 + 20_000, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), accel_cov0=-1.0)]
    got, ctx = read_all(_bag_with_imu(tmp_path / "drv.bag", raws))
    s = got.series["imu"]
    np.testing.assert_array_equal(s["t"], [T0 + 10_000, T0 + 20_000])
    np.testing.assert_allclose([s["gx"][0], s["gy"][0], s["gz"][0]],
                               np.degrees([0.1, -0.2, 0.3]), rtol=1e-12)
    np.testing.assert_allclose([s["ax"][0], s["ay"][0], s["az"][0]], [0.0, -1.0, 0.5],
                               rtol=1e-12, atol=1e-15)
    assert np.isnan([s["ax"][1], s["ay"][1], s["az"][1]]).all()   # covariance -1: absent
    assert ctx.metrics["rosbag"]["imu_topic"] == "/dvs/imu"


def test_imu_bad_input_names_the_file_and_field(tmp_path):
    # no IMU topic: no series, unless one is asked for by name
    plain = write_bag(tmp_path / "plain.bag", stream(n=200))
    got, ctx = read_all(plain)
    assert "imu" not in got.series and ctx.metrics["rosbag"]["imu_topic"] is None
    with pytest.raises(DataError, match=r"plain\.bag: no IMU topic '/dvs/imu'; "
                                        r"sensor_msgs/msg/Imu topics: none"):
        read_all(plain, imu_topic="/dvs/imu")
    with pytest.raises(DataError, match=r"plain\.bag: topic '/dvs/events' has type "
                                        r"dvs_msgs/msg/EventArray; expected sensor_msgs/msg/Imu"):
        read_all(plain, imu_topic="/dvs/events")
    good = _imu_msg(T0 + 10_000, (0.1, 0.2, 0.3), (0.0, -9.8, 0.0))
    two = _bag_with_imu(tmp_path / "two.bag", [good], imu_topics=("/a/imu", "/b/imu"))
    with pytest.raises(DataError, match=r"two\.bag: several sensor_msgs/msg/Imu topics "
                                        r"\['/a/imu', '/b/imu'\]; set imu_topic"):
        read_all(two)
    assert len(read_all(two, imu_topic="/b/imu")[0].series["imu"]) == 1
    nogyro = _bag_with_imu(tmp_path / "nogyro.bag",
                           [good, _imu_msg(T0 + 20_000, (0, 0, 0), (0, 0, 0), gyro_cov0=-1.0)])
    with pytest.raises(DataError, match=r"nogyro\.bag: topic '/dvs/imu' message 1: field "
                                        r"angular_velocity_covariance\[0\] is -1"):
        read_all(nogyro)
    nan = _bag_with_imu(tmp_path / "nan.bag",
                        [_imu_msg(T0 + 10_000, (0.1, float("nan"), 0.3), (0.0, -9.8, 0.0))])
    with pytest.raises(DataError, match=r"nan\.bag: topic '/dvs/imu' message 0: field "
                                        r"angular_velocity\.y is not finite"):
        read_all(nan)
    back = _bag_with_imu(tmp_path / "back.bag",
                         [good, _imu_msg(T0 + 5_000, (0.1, 0.2, 0.3), (0.0, -9.8, 0.0))])
    with pytest.raises(DataError, match=r"back\.bag: IMU sample 1: timestamp goes backwards"):
        read_all(back)
    # a sensor_msgs/Imu of another layout (another definition: another MD5)
    import hashlib

    odd = tmp_path / "odd.bag"
    w = Writer1(odd)
    w.open()
    ev = w.add_connection("/dvs/events", EVENT_ARRAY, typestore=typestore(False))
    w.write(ev, 1, _msg([1], [3], [T0], [1]))
    conn = w.add_connection("/dvs/imu", "sensor_msgs/msg/Imu",
                            msgdef="float64 wx\nfloat64 wy\nfloat64 wz\n",
                            md5sum=hashlib.md5(b"float64 wx\nfloat64 wy\nfloat64 wz")
                            .hexdigest())  # the ROS 1 MD5 of that definition
    w.write(conn, 2, good)
    w.close()
    with pytest.raises(DataError, match=r"odd\.bag: topic '/dvs/imu': sensor_msgs/msg/Imu "
                                        r"with MD5 27227173eb5cfc3e03642a8b2c48696c, a layout "
                                        r"other than sensor_msgs'"):
        read_all(odd)
