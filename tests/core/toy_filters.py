"""Small filters for testing the framework itself (registered as a plugin module in tests)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from evchain import EventPacket, Filter, FilterParams, FlowPacket, FramePacket, Geometry, hookimpl
from evchain.core.series import FOE, SeriesDef
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
    output_paths = ("path",)

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


COUNT = SeriesDef("count", [("t", "i8"), ("n", "i8")], "events per packet")


class CutDependent(Filter):
    """Broken on purpose: its series depends on where packets are cut."""

    name = "toy_cut_dependent"
    consumes = EventPacket
    adds_series = (COUNT,)

    class Params(FilterParams):
        pass

    def process(self, packet):
        return packet.with_series(COUNT.name, COUNT.array(t=[packet.t_start], n=[len(packet)]))


class ToyFoe(Filter):
    """A fixed FOE at (1, 2) every 10 ms; ``broken`` makes it break its series declaration:
    ``silent`` adds nothing, ``dtype`` adds its entries with another dtype, ``undeclared`` adds
    a series it does not declare."""

    name = "toy_foe"
    consumes = EventPacket
    adds_series = (FOE,)

    class Params(FilterParams):
        broken: Literal["no", "silent", "dtype", "undeclared"] = "no"

    def reset(self):
        self.next = None

    def process(self, packet):
        if self.next is None:
            self.next = -(-packet.t_start // 10_000) * 10_000
        t = np.arange(self.next, packet.t_end, 10_000, dtype=np.int64)
        self.next = int(t[-1]) + 10_000 if len(t) else self.next
        entries = FOE.array(t=t, x=np.ones(len(t)), y=np.full(len(t), 2.0))
        broken = self.params.broken
        if broken == "silent":
            return packet
        if broken == "dtype":
            entries = entries[["t", "x", "y"]].astype([("t", "i8"), ("x", "f8"), ("y", "f8")])
        if broken == "undeclared":
            packet = packet.with_series(COUNT.name, COUNT.array(t=t, n=np.zeros(len(t))))
        return packet.with_series(FOE.name, entries)


class ToyFoeReader(Filter):
    """Needs the ``foe`` series (passes packets on)."""

    name = "toy_foe_reader"
    consumes = EventPacket
    needs_series = (FOE,)

    def process(self, packet):
        return packet


class ToyScorer(Filter):
    """Writes ``metrics.scored`` (events seen x weight) at the end; pass-through."""

    name = "toy_scorer"
    consumes = EventPacket

    class Params(FilterParams):
        weight: int = 1

    def reset(self):
        self.count = 0

    def process(self, packet):
        self.count += self.params.weight * len(packet)
        return packet

    def flush(self):
        self.context.metrics[self.metrics_key("scored")] = {"count": self.count}


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
    return [ToySource, ToyFrames, ToyFlow, ToyWriter, CutDependent, Mutator, ToyFoe,
            ToyFoeReader, ToyScorer]
