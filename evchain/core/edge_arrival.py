"""When the edge that fired each event reached its pixel, for the flow stages' ``t_edge``.

An edge crossing a pixel fires a run of same-polarity events spread over the crossing (the
contrast is several thresholds, or the rendered edge steps across sub-pixel samples). The flow
stages give flow to only some of them, so two pixels' flow-event times may be an early event
of one crossing and a late one of the next: a slow edge's pixel-to-pixel time is then off by
a large part of itself. The first event of each run is the edge's arrival; ``ttc``'s baseline
compares arrivals (docs/explanation/foe_ttc.md, "Edge arrival times").
"""

from __future__ import annotations

import numpy as np

from evchain.core.packets import EventPacket

#: a pixel's run of same-polarity events ends after a pause this long (µs): the slowest edges
#: that matter, a far obstacle's near the FOE, cross a pixel in a few tenths of a second
RUN_GAP_US = 1_000_000


class EdgeArrivals:
    """Per-pixel runs of same-polarity events over a stream of packets of one sensor."""

    def __init__(self, height: int, width: int, gap_us: int = RUN_GAP_US):
        from evchain.kernels.edge_arrival import new_state

        self.gap_us = int(gap_us)
        self._state = new_state(height, width)

    def of(self, packet: EventPacket) -> np.ndarray:
        """The arrival time (int64 µs) of every event of ``packet``, in order."""
        from evchain.kernels.edge_arrival import arrivals

        out = np.empty(len(packet), np.int64)
        if len(packet):
            arrivals(packet.x, packet.y, packet.t, packet.p, *self._state, self.gap_us, out)
        return out
