"""DVS events in ROS bags through ``rosbags``: source ``rosbag`` and sink ``rosbag_writer``.

Messages are ``dvs_msgs/msg/EventArray`` (``header``, ``height``, ``width``, ``events[]`` of
``dvs_msgs/msg/Event {uint16 x, uint16 y, time ts, bool polarity}``), as published by the
rpg_dvs_ros drivers and stored in most DVS datasets recorded with ROS.

* Bags: a ROS 1 ``.bag`` file or a ROS 2 bag folder (sqlite3 or mcap) for reading, through
  ``rosbags.highlevel.AnyReader``; ``rosbags.rosbag1`` / ``rosbag2`` writers for writing.
* Time: event times are kept **absolute**: ``ts.sec * 1e6 + ts.nsec // 1000`` int64 µs (ROS
  time is usually Unix time, so values are around 1.7e15). Sub-microsecond parts are
  truncated. The first packet starts at the first event's time.
* Polarity: ``true`` is ON (+1), ``false`` OFF (-1).
* Geometry: the ``width``/``height`` fields of the first message on the topic, unless given.
* Writing: one EventArray per non-empty packet (empty packets are not written), header stamp
  and bag time = the packet's last event time, ``seq`` counting from 0 (ROS 1).
* IMU: ``sensor_msgs/msg/Imu`` messages become the series ``imu``: header stamp in µs,
  angular velocity converted from rad/s to deg/s, linear acceleration from m/s² to g
  (9.80665 m/s² per g), no temperature (NaN). The axes are kept: the messages are taken to be
  in the camera's optical frame (x right, y down, z forward), as rpg_dvs_ros' DAVIS driver
  publishes them (it negates libcaer's x and z to "align axes with camera frame"), which is
  evchain's camera frame; a driver with other axes shows up in ``imu_truth``'s axis check.
  The writer writes the series back the same way, one message per sample.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, Geometry
from evchain.core.series import IMU
from evchain.errors import ConfigError, DataError
from evchain.io.atomic import AtomicFile, partial_path
from evchain.io.slicing import ImuSlicer, attach_imu, slice_stream
from pydantic import Field

from evchain_ros.msgs import (
    EVENT_ARRAY,
    IMU_MSG,
    ROS1_MD5,
    LayoutError,
    decode,
    decode_imu,
    encode,
    encode_imu,
    imu_md5,
    typestore,
)

#: IMU messages converted at a time
IMU_BATCH = 1000


def _rosbags():
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise ConfigError("ROS bags need rosbags: pip install rosbags") from None
    return AnyReader


class RosbagSource(Filter):
    """Read DVS events (dvs_msgs/EventArray) and IMU samples (sensor_msgs/Imu) from a ROS 1
    .bag file or a ROS 2 bag folder.

    The IMU topic's messages become the series ``imu`` (camera axes; deg/s and g, converted
    from ROS's rad/s and m/s²; every packet carries it, empty where its slice has no sample);
    a bag without one gives no series. Samples before the first event's slice or after the
    last one's are not delivered (counted in the metrics).
    """

    name = "rosbag"
    produces = EventPacket
    adds_series = (IMU,)
    input_paths = ("path",)

    class Params(FilterParams):
        path: str = Field(description="ROS 1 .bag file or ROS 2 bag folder")
        topic: str = Field("/dvs/events", description="topic with dvs_msgs/EventArray messages")
        packet_us: int = Field(10_000, ge=1, description="slice duration of each packet")
        width: int | None = Field(None, ge=1, description="sensor width (default: from the "
                                  "first message)")
        height: int | None = Field(None, ge=1, description="sensor height (default: from the "
                                   "first message)")
        imu: bool = Field(True, description="read sensor_msgs/Imu messages into the series "
                          "imu (camera axes, deg/s and g); false: ignore them")
        imu_topic: str | None = Field(None, description="topic with sensor_msgs/Imu messages; "
                                      "default: the bag's only such topic, if it has one "
                                      "(rpg_dvs_ros publishes /dvs/imu)")

    @classmethod
    def series_added(cls, params):
        """``imu`` unless ``imu`` is false."""
        return (IMU,) if params.imu else ()

    def setup(self, params, context):
        AnyReader = _rosbags()
        self.path = Path(params.path)
        if not self.path.exists():
            raise DataError(f"{self.path}: not found; expected a ROS 1 .bag file or a ROS 2 "
                            "bag folder")
        self.reader = None
        try:
            reader = AnyReader([self.path], default_typestore=typestore(ros2=True))
            reader.open()
            self.reader = reader
        except Exception as exc:  # rosbags raises several types for unreadable input
            raise DataError(f"{self.path}: not a readable ROS bag (a ROS 1 .bag file or a "
                            f"ROS 2 bag folder): {exc}") from None
        try:
            context.geometry = self._check(params)
        except BaseException:
            self.close()  # the chain may not call close() when setup fails
            raise
        super().setup(params, context)

    def _check(self, params) -> Geometry:
        """Find the topic, check its type, and the sensor size."""
        self.ros2 = bool(self.reader.is2)
        self.connections = [c for c in self.reader.connections if c.topic == params.topic]
        if not self.connections:
            topics = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(self.reader.topics.items()))
            raise DataError(f"{self.path}: no topic {params.topic!r}; topics: {topics or 'none'}")
        types = {c.msgtype for c in self.connections}
        if types != {EVENT_ARRAY}:
            raise DataError(f"{self.path}: topic {params.topic!r} has type "
                            f"{', '.join(sorted(types))}; expected {EVENT_ARRAY}")
        digests = {c.digest for c in self.connections} - {"", None}
        if not self.ros2 and digests - {ROS1_MD5}:
            raise DataError(f"{self.path}: topic {params.topic!r}: {EVENT_ARRAY} with MD5 "
                            f"{', '.join(sorted(digests))}, a layout other than rpg_dvs_ros' "
                            f"(MD5 {ROS1_MD5}: header, height, width, events)")
        width, height = params.width, params.height
        if width is None or height is None:
            for _, h, w in self._messages(first_only=True):
                width, height = width or w or None, height or h or None
        if width is None or height is None:
            raise DataError(f"{self.path}: topic {params.topic!r}: no message gives the sensor "
                            "size (no messages or width/height 0); give the parameters width "
                            "and height")
        self.imu_connections = self._imu_connections(params) if params.imu else []
        return Geometry(int(width), int(height))

    def _imu_connections(self, params) -> list:
        """The connections of the IMU topic: the one named, else the bag's only
        sensor_msgs/Imu topic (none: no IMU)."""
        conns = self.reader.connections
        imu_topics = sorted({c.topic for c in conns if c.msgtype == IMU_MSG})
        topic = params.imu_topic
        if topic is None:
            if len(imu_topics) > 1:
                raise DataError(f"{self.path}: several {IMU_MSG} topics {imu_topics}; set "
                                "imu_topic to the one to read")
            if not imu_topics:
                return []
            topic = imu_topics[0]
        mine = [c for c in conns if c.topic == topic]
        if not mine:
            raise DataError(f"{self.path}: no IMU topic {topic!r}; {IMU_MSG} topics: "
                            f"{imu_topics or 'none'}")
        types = {c.msgtype for c in mine}
        if types != {IMU_MSG}:
            raise DataError(f"{self.path}: topic {topic!r} has type {', '.join(sorted(types))}; "
                            f"expected {IMU_MSG} for imu_topic")
        digests = {c.digest for c in mine} - {"", None}
        if not self.ros2 and digests - {imu_md5()}:
            raise DataError(f"{self.path}: topic {topic!r}: {IMU_MSG} with MD5 "
                            f"{', '.join(sorted(digests))}, a layout other than sensor_msgs' "
                            f"(MD5 {imu_md5()})")
        return mine

    def time_span_us(self):
        return None  # bag times are receive times, not event times

    def _messages(self, first_only: bool = False):
        """``(columns, height, width)`` per message, in bag order."""
        for i, (conn, _, raw) in enumerate(self.reader.messages(connections=self.connections)):
            try:
                h, w, cols = decode(raw, self.ros2)
            except LayoutError as exc:
                raise DataError(f"{self.path}: topic {conn.topic!r} message {i}: not a "
                                f"{EVENT_ARRAY} ({exc})") from None
            yield cols, h, w
            if first_only:
                return

    def packets(self) -> Iterator[EventPacket]:
        packets = slice_stream(self._chunks(), self.context.geometry, self.params.packet_us)
        c = self.imu_connections
        imu = ImuSlicer(self._imu_batches(), str(self.path)) if c else None
        metrics = {"path": str(self.path), "imu_topic": c[0].topic if c else None}
        yield from attach_imu(packets, imu, metrics)
        self.context.metrics[self.id] = metrics

    def _imu_batches(self) -> Iterator[np.ndarray]:
        """The IMU topic's samples as series entries, through a reader of its own (the event
        messages are read at the same time)."""
        AnyReader = _rosbags()
        topic = self.imu_connections[0].topic
        reader = AnyReader([self.path], default_typestore=typestore(ros2=self.ros2))
        reader.open()
        self.imu_reader = reader
        try:
            conns = [c for c in reader.connections if c.topic == topic]
            rows: list[tuple] = []
            for i, (_, _, raw) in enumerate(reader.messages(connections=conns)):
                try:
                    t, gyro, accel, has_gyro, has_accel = decode_imu(raw, self.ros2)
                except LayoutError as exc:
                    raise DataError(f"{self.path}: topic {topic!r} message {i}: not a "
                                    f"{IMU_MSG} ({exc})") from None
                where = f"{self.path}: topic {topic!r} message {i}"
                if not has_gyro:
                    raise DataError(f"{where}: field angular_velocity_covariance[0] is -1: the "
                                    "message carries no angular velocity; expected a gyro")
                if not np.all(np.isfinite(gyro)):
                    axis = "xyz"[int(np.argmax(~np.isfinite(gyro)))]
                    raise DataError(f"{where}: field angular_velocity.{axis} is not finite")
                if not has_accel:
                    accel = np.full(3, np.nan)
                rows.append((t, *accel, *gyro, np.nan))
                if len(rows) == IMU_BATCH:
                    yield np.array(rows, IMU.dtype)
                    rows = []
            if rows:
                yield np.array(rows, IMU.dtype)
        finally:
            if self.imu_reader is reader:  # not closed by close() already
                reader.close()
                self.imu_reader = None

    def _chunks(self) -> Iterator[dict[str, np.ndarray]]:
        g, topic = self.context.geometry, self.params.topic
        done, last = 0, None
        for i, (cols, _, _) in enumerate(self._messages()):
            t, x, y = cols["t"], cols["x"], cols["y"]
            if not len(t):
                continue
            back = np.diff(t if last is None else np.concatenate([[last], t])) < 0
            if back.any():
                j = int(np.argmax(back)) + (1 if last is None else 0)
                raise DataError(f"{self.path}: topic {topic!r} message {i} event {j} (event "
                                f"{done + j} of the topic): timestamp goes backwards")
            bad = (x >= g.width) | (y >= g.height)
            if bad.any():
                j = int(np.argmax(bad))
                raise DataError(f"{self.path}: topic {topic!r} message {i} event {j} at "
                                f"({x[j]}, {y[j]}) outside the {g.width}x{g.height} sensor")
            yield cols
            done += len(t)
            last = int(t[-1])

    def close(self):
        for name in ("reader", "imu_reader"):
            reader = getattr(self, name, None)
            if reader is not None:
                reader.close()
                setattr(self, name, None)


class RosbagWriter(Filter):
    """Write events as dvs_msgs/EventArray messages (one per packet) to a ROS bag; pass them on.

    The series ``imu``, when the packets carry it, goes to ``imu_topic`` as sensor_msgs/Imu
    messages (one per sample, camera axes, rad/s and m/s²; bag time = the sample's time).
    """

    name = "rosbag_writer"
    consumes = EventPacket
    optional_series = (IMU,)
    output_paths = ("path",)

    class Params(FilterParams):
        path: str = Field("events.bag", description="output .bag file (ros1) or bag folder "
                          "(ros2), relative to the run folder")
        topic: str = Field("/dvs/events", description="topic name")
        format: Literal["ros1", "ros2"] = Field("ros1", description="ros1: a .bag file; "
                                                "ros2: a bag folder (version 9)")
        storage: Literal["sqlite3", "mcap"] = Field("sqlite3", description="ROS 2 storage "
                                                    "format (ignored for ros1)")
        compression: Literal["none", "bz2", "lz4"] = Field("none", description="ROS 1 chunk "
                                                           "compression (ignored for ros2)")
        frame_id: str = Field("dvs", description="header.frame_id of every message")
        imu_topic: str = Field("/dvs/imu", description="topic of the sensor_msgs/Imu messages "
                               "(written when the packets carry the series imu)")

    def setup(self, params, context):
        try:
            import rosbags.rosbag1  # noqa: F401
        except ImportError:
            raise ConfigError("ROS bags need rosbags: pip install rosbags") from None
        self.writer = None
        super().setup(params, context)

    def reset(self):
        self._abort()
        self.path = self.context.output_path(self.params.path)
        self.tmp = partial_path(self.path)
        self.ros2 = self.params.format == "ros2"
        self.seq = 0
        self.imu_seq = 0
        self.imu_connection = None
        self.geometry = None

    def _open(self, geometry: Geometry) -> None:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.tmp.is_dir():
            shutil.rmtree(self.tmp)
        elif self.tmp.exists():
            self.tmp.unlink()
        if self.ros2:  # NAME.partial/NAME/, so the storage file inside is NAME/NAME.db3
            self.tmp.mkdir()
            self.out = AtomicFile.reserve(self.path, self.tmp / self.path.name)
            plugin = getattr(StoragePlugin, self.params.storage.upper())
            writer = Writer2(self.out.tmp, version=9, storage_plugin=plugin)
        else:
            self.out = AtomicFile.reserve(self.path, self.tmp)
            writer = Writer1(self.out.tmp)
            if self.params.compression != "none":
                writer.set_compression(getattr(Writer1.CompressionFormat,
                                               self.params.compression.upper()))
        try:
            writer.open()
            self.connection = writer.add_connection(self.params.topic, EVENT_ARRAY,
                                                    typestore=typestore(self.ros2))
        except Exception as exc:
            raise DataError(f"{self.path}: cannot create the ROS bag: {exc}") from None
        self.writer = writer
        self.geometry = geometry

    def process(self, packet: EventPacket) -> EventPacket:
        if self.writer is None:
            self._open(packet.geometry)
        elif packet.geometry.shape != self.geometry.shape:
            raise DataError(f"{self.path}: packet at {packet.t_start} us is "
                            f"{packet.geometry.width}x{packet.geometry.height}, the bag was "
                            f"opened for {self.geometry.width}x{self.geometry.height}")
        if len(packet):
            t0, t1 = int(packet.t[0]), int(packet.t[-1])
            top = 2**31 if self.ros2 else 2**32
            if t0 < 0 or t1 >= top * 1_000_000:
                raise DataError(f"{self.path}: event times {t0}..{t1} us do not fit ROS time "
                                f"(0 <= sec < 2^{31 if self.ros2 else 32})")
            raw = encode(packet.x, packet.y, packet.t, packet.p, height=self.geometry.height,
                         width=self.geometry.width, seq=self.seq, stamp_us=t1,
                         frame_id=self.params.frame_id, ros2=self.ros2)
            self.writer.write(self.connection, t1 * 1000, raw)
            self.seq += 1
        imu = packet.series.get(IMU.name)
        if imu is not None and len(imu):
            self._write_imu(imu)
        return packet

    def _write_imu(self, imu: np.ndarray) -> None:
        if self.imu_connection is None:
            try:
                self.imu_connection = self.writer.add_connection(
                    self.params.imu_topic, IMU_MSG, typestore=typestore(self.ros2))
            except Exception as exc:
                raise DataError(f"{self.path}: cannot add the IMU topic "
                                f"{self.params.imu_topic!r}: {exc}") from None
        accel = np.stack([imu["ax"], imu["ay"], imu["az"]], 1)
        gyro = np.stack([imu["gx"], imu["gy"], imu["gz"]], 1)
        for t, a, g in zip(imu["t"].tolist(), accel, gyro, strict=True):
            raw = encode_imu(t, g, a, seq=self.imu_seq, frame_id=self.params.frame_id,
                             ros2=self.ros2)
            self.writer.write(self.imu_connection, t * 1000, raw)
            self.imu_seq += 1

    def flush(self):
        if self.writer is None:
            geometry = self.context.geometry
            if geometry is None:
                raise DataError(f"{self.path}: no packets and no sensor geometry; cannot write "
                                "a ROS bag")
            self._open(geometry)
        self.writer.close()
        self.writer = None
        self._remove_old()
        self.out.commit()
        if self.ros2:
            self.tmp.rmdir()
        return None

    def _abort(self) -> None:
        writer = getattr(self, "writer", None)
        if writer is None:
            return
        self.writer = None
        try:
            writer.close()
        except Exception:  # closing only tidies the partial output; the run has failed anyway
            pass
        self._remove_old()
        self.out.abort()

    def _remove_old(self) -> None:
        """Remove the output of an earlier run: a bag file, or a folder that is a ROS 2 bag."""
        if self.path.is_dir():
            if not (self.path / "metadata.yaml").is_file():
                raise DataError(f"{self.path}: exists and is a folder but not a ROS 2 bag; "
                                "not replacing it")
            shutil.rmtree(self.path)
        elif self.path.exists() or self.path.is_symlink():
            self.path.unlink()

    def close(self):
        self._abort()
