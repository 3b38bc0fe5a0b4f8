"""Small filters for testing the framework itself (registered as a plugin module in tests)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from evchain import EventPacket, Filter, FilterParams, FlowPacket, FramePacket, Geometry, hookimpl
from evchain.core.packets import series_array
from evchain.io.atomic import AtomicFile
from evchain.testing.synthetic import random_events, textured_frames

CLOSED: list[str] = []


class ToySource(Filter):
    """Random events in packets of 10 ms."""

    name = "toy_source"
    produces = EventPacket

    class Params(FilterParams):
        packets: int = Field(3, ge=1, description="number of packets")
        events_per_packet: int = Field(100, ge=0)
        fail_at_packet: int | None = Field(None, description="raise in this packet")
        width: int = Field(32, ge=1)

    def setup(self, params, context):
        super().setup(params, context)
        context.geometry = Geometry(params.width, 24)

    def packets(self):
        for i in range(self.params.packets):
            if i == self.params.fail_at_packet:
                raise ValueError("boom")
            yield random_events(self.params.events_per_packet, self.context.geometry,
                                i * 10_000, (i + 1) * 10_000, seed=i)

    def time_span_us(self):
        return (0, self.params.packets * 10_000)

    def close(self):
        CLOSED.append(self.id)


class ToyFrames(Filter):
    """Frames of a moving texture."""

    name = "toy_frames"
    produces = FramePacket

    class Params(FilterParams):
        pass

    def setup(self, params, context):
        super().setup(params, context)
        context.geometry = Geometry(16, 12)

    def packets(self):
        yield textured_frames(3, self.context.geometry)


class ToyFlow(Filter):
    """Gives every event the flow (1, 0) px/s."""

    name = "toy_flow"
    consumes = EventPacket
    produces = FlowPacket

    class Params(FilterParams):
        mode: Literal["a", "b"] = "a"
        gain: float = Field(1.0, gt=0, le=10, description="flow scale")

    def process(self, packet):
        n = len(packet)
        return FlowPacket.from_events(packet, np.arange(n), np.full(n, self.params.gain),
                                      np.zeros(n))


class ToyWriter(Filter):
    """Writes the number of events atomically; fails on request."""

    name = "toy_writer"
    consumes = EventPacket

    class Params(FilterParams):
        path: str = "count.txt"
        fail: bool = False

    def reset(self):
        self.count = 0

    def setup(self, params, context):
        super().setup(params, context)
        self.file = AtomicFile(context.output_path(params.path))

    def process(self, packet):
        if self.params.fail:
            raise RuntimeError("disk on fire")
        self.count += len(packet)
        return packet

    def flush(self):
        self.file.write(str(self.count).encode())
        self.file.commit()
        self.context.metrics["toy"] = {"count": self.count}

    def close(self):
        self.file.abort()
        CLOSED.append(self.id)


class CutDependent(Filter):
    """Broken on purpose: its series depends on where packets are cut."""

    name = "toy_cut_dependent"
    consumes = EventPacket

    class Params(FilterParams):
        pass

    def process(self, packet):
        entry = series_array([("t", "i8"), ("n", "i8")], t=[packet.t_start], n=[len(packet)])
        return packet.with_series("count", entry)


class Mutator(Filter):
    """Broken on purpose: writes into its input."""

    name = "toy_mutator"
    consumes = EventPacket

    class Params(FilterParams):
        pass

    def process(self, packet):
        packet.x[:] = 0
        return packet


@hookimpl
def evchain_filters():
    return [ToySource, ToyFrames, ToyFlow, ToyWriter, CutDependent, Mutator]
