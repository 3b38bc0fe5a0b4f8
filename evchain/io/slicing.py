"""Cutting a stream of event column chunks into packets of consecutive time slices: of a fixed
duration (:func:`slice_stream`), or as the chunks arrive (:func:`slice_as_delivered`, for live
streams)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from evchain.core.packets import EventPacket, Geometry


def slice_stream(chunks: Iterator[dict[str, np.ndarray]], geometry: Geometry,
                 packet_us: int) -> Iterator[EventPacket]:
    """Cut time-ordered column chunks (``x, y, t, p`` arrays of any length) into packets of
    consecutive ``packet_us`` slices, from the first event's time to one past the last one's.

    A slice is emitted only once a later event shows it complete, so chunk boundaries never
    change the packets. Memory is bounded by one chunk plus one slice.
    """
    buf: dict[str, np.ndarray] | None = None
    t0 = None
    for cols in chunks:
        if not len(cols["t"]):
            continue
        buf = cols if buf is None else {c: np.concatenate([buf[c], cols[c]]) for c in buf}
        if t0 is None:
            t0 = int(buf["t"][0])
        limit = int(buf["t"][-1])  # later chunks may still hold events at this very time
        while t0 + packet_us <= limit:
            buf, t0 = (yield from _emit(buf, geometry, t0, t0 + packet_us))
    if buf is None:
        return
    limit = int(buf["t"][-1]) + 1 if len(buf["t"]) else t0
    while t0 < limit:
        buf, t0 = (yield from _emit(buf, geometry, t0, min(t0 + packet_us, limit)))


def _emit(buf, geometry, t0, t1):
    k = int(np.searchsorted(buf["t"], t1, "left"))
    yield EventPacket(geometry=geometry, t_start=t0, t_end=t1,
                      **{c: v[:k] for c, v in buf.items()})
    return {c: v[k:] for c, v in buf.items()}, t1


def slice_as_delivered(chunks: Iterator[dict[str, np.ndarray]],
                       geometry: Geometry) -> Iterator[EventPacket]:
    """One packet per time-ordered column chunk, as soon as it comes, with consecutive slices
    from the first event's time to one past the last one's.

    The events at a chunk's last time wait for the next chunk (it may hold more at that very
    time) and come with it, or at the end of the stream: each packet ends at its chunk's last
    time, so a chunk whose events all share one time gives no packet of its own.
    """
    held: dict[str, np.ndarray] | None = None
    t0 = None
    for cols in chunks:
        if not len(cols["t"]):
            continue
        if held is not None:
            cols = {c: np.concatenate([held[c], cols[c]]) for c in cols}
        if t0 is None:
            t0 = int(cols["t"][0])
        last = int(cols["t"][-1])
        if last > t0:
            held, t0 = (yield from _emit(cols, geometry, t0, last))
        else:
            held = cols
    if held is not None and len(held["t"]):
        yield from _emit(held, geometry, t0, int(held["t"][-1]) + 1)
