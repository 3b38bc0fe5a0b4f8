"""``polarity``: keep ON events, OFF events, or both."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket


class Polarity(Filter):
    """Keep only ON (+1) or only OFF (-1) events; ``both`` passes everything."""

    name = "polarity"
    consumes = EventPacket
    produces = EventPacket

    class Params(FilterParams):
        keep: Literal["on", "off", "both"] = Field("on", description="which events pass")

    def process(self, packet: EventPacket) -> EventPacket:
        if self.params.keep == "both":
            return packet
        return packet.select(packet.p > 0 if self.params.keep == "on" else packet.p < 0)
