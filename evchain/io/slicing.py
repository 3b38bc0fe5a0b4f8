"""Cutting a stream of event column chunks into packets of consecutive time slices."""

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
