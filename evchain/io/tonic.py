"""Conversions between evchain's event packets and tonic's structured events.

tonic (``pip install 'evchain[tonic]'``, used only to apply its transforms; these functions
need only numpy) keeps events as one numpy structured array with fields ``x``, ``y`` (int16),
``t`` (int64, µs) and ``p`` (bool, True = ON), and a sensor size ``(width, height,
polarities)``; its ``ToFrame`` puts polarity 0 (OFF) in channel 0 and 1 (ON) in channel 1.
evchain's packets are separate columns with ``p`` -1/+1 (:mod:`evchain.core.packets`).

* :func:`to_tonic` packet -> tonic events, :func:`sensor_size` geometry -> tonic's size,
* :func:`from_tonic` tonic events (tonic's dtype, or the plain-int ones of many tonic datasets,
  in any field order) -> one packet, checked,
* :func:`packets_from_tonic` the same cut into consecutive time slices, for filters.

To run a pipeline on tonic events, write them as HDF5 and read them with the ``hdf5`` source:
``write_hdf5("events.h5", from_tonic(events, size))``.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from evchain.core.packets import EventPacket, Geometry
from evchain.errors import DataError
from evchain.io.slicing import slice_stream

#: tonic's event dtype (``tonic.io.events_struct``)
TONIC_DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.int64), ("p", bool)])
FIELDS = ("x", "y", "t", "p")


def sensor_size(geometry: Geometry) -> tuple[int, int, int]:
    """tonic's sensor size ``(width, height, 2)``."""
    return (geometry.width, geometry.height, 2)


def to_tonic(events: EventPacket) -> np.ndarray:
    """The events as tonic's structured array (``p`` True for ON)."""
    g = events.geometry
    limit = np.iinfo(np.int16).max + 1
    if g.width > limit or g.height > limit:
        raise DataError(f"a {g.width}x{g.height} sensor does not fit tonic's int16 x, y")
    out = np.empty(len(events), TONIC_DTYPE)
    out["x"], out["y"], out["t"] = events.x, events.y, events.t
    out["p"] = events.p > 0
    return out


def _columns(events: np.ndarray, geometry: Geometry) -> dict[str, np.ndarray]:
    names = events.dtype.names or ()
    missing = [f for f in FIELDS if f not in names]
    if missing:
        raise DataError(f"tonic events lack fields {missing}; have {list(names)} (expected x, "
                        "y, t, p)")
    for f in FIELDS:
        kind = events.dtype[f].kind
        if kind not in ("uib" if f == "p" else "ui"):
            what = "integer µs" if f == "t" else "integers"
            raise DataError(f"tonic events' field {f} has dtype {events.dtype[f]}; expected "
                            f"{what}")
    x, y, t, p = (events[f] for f in FIELDS)
    for name, v, size in (("x", x, geometry.width), ("y", y, geometry.height)):
        bad = (v < 0) | (v >= size)
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"tonic event {i}: field {name} = {v[i]} is outside the "
                            f"{geometry.width}x{geometry.height} sensor")
    if p.dtype.kind != "b":
        bad = (p < -1) | (p > 1)
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"tonic event {i}: field p = {p[i]}; expected True/False, 0/1 or "
                            "-1/+1")
        if (p == 0).any() and (p == -1).any():
            raise DataError("tonic events' field p holds both 0 and -1; expected 0/1 (tonic) "
                            "or -1/+1, not a mix")
    back = np.diff(t) < 0
    if back.any():
        i = int(np.argmax(back)) + 1
        raise DataError(f"tonic event {i} at t = {t[i]} us comes before the one ahead of it "
                        f"({t[i - 1]} us); sort first: events[np.argsort(events['t'], "
                        "kind='stable')]")
    return {"x": x.astype(np.uint16), "y": y.astype(np.uint16), "t": t.astype(np.int64),
            "p": np.where(p > 0, 1, -1).astype(np.int8)}


def _geometry(size: tuple[int, ...] | Geometry) -> Geometry:
    return size if isinstance(size, Geometry) else Geometry(int(size[0]), int(size[1]))


def from_tonic(events: np.ndarray, size: tuple[int, ...] | Geometry,
               t_start: int | None = None, t_end: int | None = None) -> EventPacket:
    """One packet from tonic events; ``size`` is tonic's ``(width, height, polarities)`` or a
    :class:`Geometry`. The slice defaults to ``[t[0], t[-1] + 1)``. Bad fields, coordinates
    outside the sensor, other polarity values and unsorted times are :class:`DataError`."""
    geometry = _geometry(size)
    cols = _columns(np.asarray(events), geometry)
    t = cols["t"]
    if t_start is None:
        t_start = int(t[0]) if len(t) else 0
    if t_end is None:
        t_end = int(t[-1]) + 1 if len(t) else t_start
    return EventPacket(geometry=geometry, t_start=t_start, t_end=t_end, **cols).validate()


def packets_from_tonic(events: np.ndarray, size: tuple[int, ...] | Geometry,
                       packet_us: int = 10_000) -> Iterator[EventPacket]:
    """tonic events as packets of consecutive ``packet_us`` slices (from the first event's
    time to one past the last one's), as a source would emit them."""
    geometry = _geometry(size)
    yield from slice_stream(iter([_columns(np.asarray(events), geometry)]), geometry, packet_us)
