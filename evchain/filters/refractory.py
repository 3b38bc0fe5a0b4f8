"""``refractory``: a per-pixel dead time after each event that passes."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket

NEVER = np.iinfo(np.int64).min // 4  # "no event yet": far enough in the past, no overflow


class Refractory(Filter):
    """Drop events that arrive within ``period_us`` after the pixel's last passed event.

    A pixel that passed an event at time t0 is dead until t0 + period_us (an event exactly at
    t0 + period_us passes). Blocked events do not extend the dead time. With ``per_polarity``
    ON and OFF events of a pixel have separate dead times. State persists across packets, so
    where the stream is cut does not matter.
    """

    name = "refractory"
    consumes = EventPacket
    produces = EventPacket

    class Params(FilterParams):
        period_us: int = Field(1000, ge=0, le=10_000_000,
                               description="dead time after a passed event, µs")
        per_polarity: bool = Field(False, description="separate dead times for ON and OFF")

    def reset(self) -> None:
        self._last: np.ndarray | None = None

    def _state(self, packet: EventPacket) -> np.ndarray:
        shape = (2 if self.params.per_polarity else 1, *packet.geometry.shape)
        if self._last is None or self._last.shape != shape:
            self._last = np.full(shape, NEVER, np.int64)
        return self._last

    def process(self, packet: EventPacket) -> EventPacket:
        from evchain.kernels.refractory import refractory

        last = self._state(packet)
        keep = np.empty(len(packet), np.bool_)
        refractory(packet.x, packet.y, packet.t, packet.p, last, self.params.period_us,
                   self.params.per_polarity, keep)
        return packet.select(keep)
