"""``dvs_msgs/msg/EventArray`` for rosbags, and a numpy codec for its event array;
``sensor_msgs/msg/Imu`` through rosbags' own (de)serialisation (one message per sample).

The types are registered in rosbags typestores from their ``.msg`` definitions (ROS 1 with
``time``, ROS 2 with ``builtin_interfaces/Time``). rosbags serialises the message header; the
event array itself — 13 packed bytes per event in ROS 1, CDR-aligned 14/16-byte records in ROS 2
— is read and written as numpy record views, because building one Python object per event
(rosbags' generic path) runs at about 50 000 events/s. The tests check these views byte for
byte against rosbags' own serialisation of the same messages.

Layouts (offsets in bytes; CDR offsets count from the end of the 4-byte encapsulation header)::

    ROS 1:  u32 seq, u32 sec, u32 nsec, u32 len + frame_id, u32 height, u32 width, u32 n,
            n x (u16 x, u16 y, u32 sec, u32 nsec, u8 polarity)                    13 bytes each
    CDR:    i32 sec, u32 nanosec, u32 len + frame_id + NUL, pad to 4, u32 height, u32 width,
            u32 n, event 0 at a multiple of 4: x@0 y@2 sec@4 nanosec@8 polarity@12 (14 bytes
            with padding), events 1.. at 2 mod 4: x@0 y@2 sec@6 nanosec@10 polarity@14
            (16 bytes with padding; the last one ends after its polarity byte)
"""

from __future__ import annotations

import functools
import struct

import numpy as np

EVENT_ARRAY = "dvs_msgs/msg/EventArray"
EVENT = "dvs_msgs/msg/Event"
ROS1_MD5 = "5e8beee5a6c107e504c2e78903c224b8"  # rpg_dvs_ros' dvs_msgs/EventArray (ROS 1)

MSG_ROS1 = {
    EVENT: "uint16 x\nuint16 y\ntime ts\nbool polarity\n",
    EVENT_ARRAY: "Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n",
}
MSG_ROS2 = {
    EVENT: "uint16 x\nuint16 y\nbuiltin_interfaces/Time ts\nbool polarity\n",
    EVENT_ARRAY: "std_msgs/Header header\nuint32 height\nuint32 width\n"
                 "dvs_msgs/Event[] events\n",
}

ROS1_EVENT = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"),
                       ("p", "u1")])
CDR_FIRST = np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                      "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                      "offsets": [0, 2, 4, 8, 12], "itemsize": 13})
CDR_REST = np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                     "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                     "offsets": [0, 2, 6, 10, 14], "itemsize": 15})
CDR_LE = b"\x00\x01"


class LayoutError(ValueError):
    """A message's bytes do not have the dvs_msgs/EventArray layout (the caller names where)."""


@functools.cache
def typestore(ros2: bool):
    """A rosbags typestore (Noetic or Humble) with the dvs_msgs types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    types = {}
    for name, text in (MSG_ROS2 if ros2 else MSG_ROS1).items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _cdr_events_size(n: int) -> int:
    return 0 if n == 0 else 16 * n - 3


def decode(raw, ros2: bool) -> tuple[int, int, dict[str, np.ndarray]]:
    """``(height, width, columns)`` of one serialised EventArray; columns x, y uint16,
    t int64 µs (sub-µs parts truncated), p int8 ±1."""
    buf = memoryview(raw).cast("B")
    size = len(buf)
    try:
        if ros2:
            if bytes(buf[:2]) != CDR_LE:
                raise LayoutError(f"CDR encapsulation {bytes(buf[:2])!r}; only little-endian "
                                  "plain CDR (00 01) is supported")
            (slen,) = struct.unpack_from("<I", buf, 12)
            o = 4 + (8 + 4 + slen + 3) // 4 * 4
            height, width, n = struct.unpack_from("<III", buf, o)
            start = o + 12
            need = start + _cdr_events_size(n)
            if not need <= size < need + 8:
                raise LayoutError(f"{size} bytes, expected {need} for {n} events")
            cols = [np.frombuffer(buf, CDR_FIRST, min(n, 1), start)]
            if n > 1:
                cols.append(np.ndarray((n - 1,), CDR_REST, buf, start + 14, (16,)))
        else:
            (slen,) = struct.unpack_from("<I", buf, 12)
            o = 16 + slen
            height, width, n = struct.unpack_from("<III", buf, o)
            start = o + 12
            if size != start + 13 * n:
                raise LayoutError(f"{size} bytes, expected {start + 13 * n} for {n} events")
            cols = [np.frombuffer(buf, ROS1_EVENT, n, start)]
    except struct.error as exc:
        raise LayoutError(f"{size} bytes, too short for an EventArray ({exc})") from None
    x = np.concatenate([c["x"] for c in cols]).astype(np.uint16)
    y = np.concatenate([c["y"] for c in cols]).astype(np.uint16)
    sec = np.concatenate([c["sec"] for c in cols]).astype(np.int64)
    nsec = np.concatenate([c["nsec"] for c in cols]).astype(np.int64)
    p = np.concatenate([c["p"] for c in cols])
    t = sec * 1_000_000 + nsec // 1000
    return int(height), int(width), {"x": x, "y": y, "t": t,
                                     "p": np.where(p > 0, 1, -1).astype(np.int8)}


def encode(x, y, t, p, *, height: int, width: int, seq: int, stamp_us: int, frame_id: str,
           ros2: bool) -> bytes:
    """Serialise one EventArray: rosbags writes the header, numpy the events (``t`` in µs,
    ``p`` ±1)."""
    store = typestore(ros2)
    T, H, EA = (store.types[k] for k in ("builtin_interfaces/msg/Time", "std_msgs/msg/Header",
                                         EVENT_ARRAY))
    stamp = T(sec=stamp_us // 1_000_000, nanosec=stamp_us % 1_000_000 * 1000)
    header = H(stamp=stamp, frame_id=frame_id) if ros2 else H(seq=seq, stamp=stamp,
                                                              frame_id=frame_id)
    msg = EA(header=header, height=height, width=width, events=[])
    empty = bytes(store.serialize_cdr(msg, EVENT_ARRAY) if ros2
                  else store.serialize_ros1(msg, EVENT_ARRAY))
    n = len(t)
    t = np.asarray(t, np.int64)
    if ros2:
        data = np.zeros(16 * n + 16, np.uint8)
        parts = [(np.ndarray((min(n, 1),), CDR_FIRST, data, 0), slice(0, 1)),
                 (np.ndarray((max(n - 1, 0),), CDR_REST, data, 14, (16,)), slice(1, n))]
        body = data[:_cdr_events_size(n)]
    else:
        ev = np.zeros(n, ROS1_EVENT)
        parts, body = [(ev, slice(0, n))], ev
    for view, sel in parts:
        view["x"], view["y"] = x[sel], y[sel]
        view["sec"], view["nsec"] = t[sel] // 1_000_000, t[sel] % 1_000_000 * 1000
        view["p"] = np.asarray(p[sel]) > 0
    return empty[:-4] + struct.pack("<I", n) + body.tobytes()


# -- sensor_msgs/Imu -----------------------------------------------------------------------------

IMU_MSG = "sensor_msgs/msg/Imu"
#: standard gravity, m/s² per g (sensor_msgs/Imu carries m/s², the series imu g)
STANDARD_GRAVITY = 9.80665


def imu_md5() -> str:
    """The ROS 1 MD5 of sensor_msgs/Imu (as the Noetic typestore defines it)."""
    return typestore(False).generate_msgdef(IMU_MSG)[1]


def decode_imu(raw, ros2: bool) -> tuple[int, np.ndarray, np.ndarray, bool, bool]:
    """``(t_us, gyro_dps [3], accel_g [3], has_gyro, has_accel)`` of one serialised
    sensor_msgs/Imu: the header stamp in µs (sub-µs parts truncated), the angular velocity in
    deg/s and the linear acceleration in g (from rad/s and m/s²); ``has_*`` False where the
    message's covariance marks the part as absent (element 0 = -1, REP 145)."""
    store = typestore(ros2)
    try:
        msg = (store.deserialize_cdr(raw, IMU_MSG) if ros2
               else store.deserialize_ros1(raw, IMU_MSG))
    except Exception as exc:  # rosbags raises several types for bytes of another layout
        raise LayoutError(f"{len(raw)} bytes that do not deserialise ({exc})") from None
    s = msg.header.stamp
    w, a = msg.angular_velocity, msg.linear_acceleration
    gyro = np.degrees(np.array([w.x, w.y, w.z], np.float64))
    accel = np.array([a.x, a.y, a.z], np.float64) / STANDARD_GRAVITY
    return (int(s.sec) * 1_000_000 + int(s.nanosec) // 1000, gyro, accel,
            float(msg.angular_velocity_covariance[0]) != -1.0,
            float(msg.linear_acceleration_covariance[0]) != -1.0)


def encode_imu(t_us: int, gyro_dps, accel_g, *, seq: int, frame_id: str, ros2: bool) -> bytes:
    """Serialise one sensor_msgs/Imu: stamp ``t_us``, angular velocity in rad/s and linear
    acceleration in m/s² from deg/s and g; no orientation (covariance element 0 = -1), nor
    acceleration where ``accel_g`` is not finite."""
    store = typestore(ros2)
    T, H, Q, V, M = (store.types[k] for k in (
        "builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Quaternion",
        "geometry_msgs/msg/Vector3", IMU_MSG))
    stamp = T(sec=t_us // 1_000_000, nanosec=t_us % 1_000_000 * 1000)
    header = H(stamp=stamp, frame_id=frame_id) if ros2 else H(seq=seq, stamp=stamp,
                                                              frame_id=frame_id)
    w = np.radians(np.asarray(gyro_dps, np.float64))
    a = np.asarray(accel_g, np.float64) * STANDARD_GRAVITY
    absent = np.zeros(9)
    absent[0] = -1.0
    has_accel = bool(np.all(np.isfinite(a)))
    msg = M(header=header, orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=absent.copy(),
            angular_velocity=V(x=float(w[0]), y=float(w[1]), z=float(w[2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V(*(map(float, a) if has_accel else (0.0, 0.0, 0.0))),
            linear_acceleration_covariance=np.zeros(9) if has_accel else absent.copy())
    return bytes(store.serialize_cdr(msg, IMU_MSG) if ros2 else store.serialize_ros1(msg, IMU_MSG))
