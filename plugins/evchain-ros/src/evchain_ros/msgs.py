"""``dvs_msgs/msg/EventArray`` for rosbags, and a numpy codec for its event array.

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
