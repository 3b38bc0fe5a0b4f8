"""``exact_speed``: flow events with their estimated direction and the true normal speed."""

from __future__ import annotations

import numpy as np

from evchain.core.filter import Filter
from evchain.core.packets import FlowPacket
from evchain.core.truth import FlowTruth


class ExactSpeed(Filter):
    """An oracle, placed after a flow stage: each flow event keeps its direction (the normal
    v/|v|) and gets the true normal speed, the ground truth's flow at its pixel and time
    projected on that normal. Events where the truth is undefined or the projection is not
    positive (or the event has no direction) are dropped.

    With the same events and directions, a later stage's error that remains is its model's
    error, not the flow's speeds' (docs/explanation/foe_ttc.md, "The column on other streets").
    """

    name = "exact_speed"
    consumes = FlowPacket
    produces = FlowPacket
    needs_truth = (FlowTruth,)

    def process(self, packet: FlowPacket) -> FlowPacket:
        if not len(packet):
            return packet
        vx = packet.vx.astype(np.float64)
        vy = packet.vy.astype(np.float64)
        speed = np.hypot(vx, vy)
        ux, uy = self.truth.flow(packet.x.astype(np.float64), packet.y.astype(np.float64),
                                 packet.t.astype(np.float64))
        with np.errstate(invalid="ignore", divide="ignore"):
            nx, ny = vx / speed, vy / speed
            true_speed = np.asarray(ux, np.float64) * nx + np.asarray(uy, np.float64) * ny
        keep = np.isfinite(true_speed) & (true_speed > 0)
        out = packet.select(keep)
        return out.replace(vx=(true_speed[keep] * nx[keep]).astype(np.float32),
                           vy=(true_speed[keep] * ny[keep]).astype(np.float32))
