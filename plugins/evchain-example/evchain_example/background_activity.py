"""``background_activity``: jAER-style background-activity (noise) filter."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket

NEVER = np.iinfo(np.int64).min // 4  # "no event yet": far in the past, no overflow


class BackgroundActivityFilter(Filter):
    """Pass an event only if one of its 8 neighbours had an event within ``window_us`` before it.

    As in jAER's BackgroundActivityFilter, every event (passed or not) writes its time into the
    maps of its 8 neighbours, not its own; an event passes if its own map entry is at most
    ``window_us`` old. So a pixel's own earlier events never support it, and isolated noise
    events are removed. Events at the sensor border have fewer neighbours. State persists across
    packets.
    """

    name = "background_activity"
    consumes = EventPacket
    produces = EventPacket

    class Params(FilterParams):
        window_us: int = Field(10_000, ge=0, le=10_000_000,
                               description="how recent a neighbour's event must be, µs")

    def reset(self) -> None:
        self._last: np.ndarray | None = None

    def process(self, packet: EventPacket) -> EventPacket:
        from evchain_example.kernels import background_activity  # numba: import lazily

        if self._last is None or self._last.shape != packet.geometry.shape:
            self._last = np.full(packet.geometry.shape, NEVER, np.int64)
        keep = np.empty(len(packet), np.bool_)
        background_activity(packet.x, packet.y, packet.t, self._last, self.params.window_us,
                            keep)
        return packet.select(keep)
