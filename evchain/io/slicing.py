"""Cutting a stream of event column chunks into packets of consecutive time slices, and
handing each slice the IMU samples recorded beside the events."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from evchain.core.packets import EventPacket, Geometry
from evchain.errors import DataError


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


class ImuSlicer:
    """Hands each packet of a source the IMU samples of its time slice, as the series ``imu``.

    ``chunks`` yields :data:`~evchain.core.series.IMU` arrays in time order (any length; a
    file's IMU stream read beside its events); ``where`` names the file in errors. Packets must
    come in order as consecutive slices (as :func:`slice_stream` cuts them). Every packet gets
    the series, empty where its slice has no sample. Samples before the first packet's slice
    are counted in ``before``, those after the last packet's (:meth:`finish`) in ``after``;
    neither is delivered. A sample earlier than the one before it is a
    :class:`~evchain.errors.DataError` naming ``where`` and the sample's index.
    """

    def __init__(self, chunks: Iterator[np.ndarray], where: str):
        from evchain.core.series import IMU

        self._chunks = iter(chunks)
        self._pending = np.zeros(0, IMU.dtype)
        self._last: int | None = None
        self._ended = False
        self.where = where
        self.read = 0
        self.delivered = 0
        self.before = 0
        self.after = 0

    def _pull(self) -> bool:
        """Read the next non-empty chunk into the pending samples; False at the end."""
        for chunk in self._chunks:
            if not len(chunk):
                continue
            t = chunk["t"]
            back = np.diff(t if self._last is None else np.concatenate([[self._last], t])) < 0
            if back.any():
                i = self.read + int(np.argmax(back)) + (1 if self._last is None else 0)
                raise DataError(f"{self.where}: IMU sample {i}: timestamp goes backwards")
            self.read += len(chunk)
            self._last = int(t[-1])
            self._pending = np.concatenate([self._pending, chunk]) if len(self._pending) \
                else chunk
            return True
        self._ended = True
        return False

    def attach(self, packet: EventPacket) -> EventPacket:
        """``packet`` with the samples of ``[t_start, t_end)`` as the series ``imu``."""
        from evchain.core.series import IMU

        while not self._ended and (not len(self._pending)
                                   or self._pending["t"][-1] < packet.t_end):
            self._pull()
        t = self._pending["t"]
        early = t < packet.t_start
        self.before += int(np.count_nonzero(early))
        mine = self._pending[~early & (t < packet.t_end)]
        self._pending = self._pending[t >= packet.t_end]
        self.delivered += len(mine)
        return packet.with_series(IMU.name, mine)

    def finish(self) -> None:
        """After the last packet: count the samples left over (reads the rest)."""
        while not self._ended:
            self._pull()
        self.after += len(self._pending)
        self._pending = self._pending[:0]


def attach_imu(packets: Iterator[EventPacket], imu: ImuSlicer | None,
               metrics: dict) -> Iterator[EventPacket]:
    """``packets`` with their IMU samples attached by ``imu`` (``None``: a file without IMU,
    the packets as they are). Once the packets are done, ``metrics`` gets ``imu_samples`` and,
    with an IMU, ``imu_before_events`` and ``imu_after_events`` (the samples not delivered)."""
    if imu is None:
        yield from packets
        metrics["imu_samples"] = 0
        return
    for packet in packets:
        yield imu.attach(packet)
    imu.finish()
    metrics.update(imu_samples=imu.delivered, imu_before_events=imu.before,
                   imu_after_events=imu.after)
