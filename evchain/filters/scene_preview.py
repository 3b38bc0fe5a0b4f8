"""Sink ``scene_preview``: PNGs of frame, depth and ground-truth flow at chosen times."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FramePacket
from evchain.core.truth import DepthTruth, FlowTruth
from evchain.errors import ConfigError


class ScenePreview(Filter):
    """Writes PNGs of the frame, depth and ground-truth flow (hue = direction) at chosen times.

    For each time in ``times_s`` it renders the frame exactly at that time when the source
    offers a renderer (``context.renderer``; the ``scene`` source does; times after the
    streamed stretch but inside the drive are pictured at the end), else takes the nearest
    frame of the packet; depth and flow come from the ground truth when it has them.
    ``scenarios`` additionally pictures the drive of other scenarios (same camera and speed,
    from the start of their route; ``scene`` source only), so one pipeline previews them all.
    Passes frames on unchanged.
    """

    name = "scene_preview"
    consumes = FramePacket
    produces = None
    uses_truth = (DepthTruth, FlowTruth)
    output_paths = ("out",)

    class Params(FilterParams):
        times_s: list[float] = Field([0.0], description="times (s) to picture")
        out: str = Field("preview", description="folder (relative to the run's output)")
        scenarios: list[str] = Field([], description="also picture these scenarios at times_s")

    def setup(self, params, context) -> None:
        if any(t < 0 for t in params.times_s):
            raise ConfigError(f"scene_preview: times_s must be >= 0, got {params.times_s}")
        if params.scenarios:
            from evchain.sim.renderer import SceneRenderer

            if not isinstance(context.renderer, SceneRenderer):
                raise ConfigError("scene_preview: 'scenarios' needs the 'scene' source upstream")
        super().setup(params, context)

    def reset(self) -> None:
        self.pending = sorted(set(self.params.times_s))
        self.written: list[str] = []
        self.others_done = False

    def _prefix(self) -> str:
        renderer = self.context.renderer
        return renderer.name if renderer is not None else "stream"

    def _write(self, frame: np.ndarray, t_s: float, prefix: str, truth) -> None:
        from evchain.sim.preview import write_preview

        out_dir = self.context.output_path(self.params.out)
        self.written += [str(p) for p in write_preview(frame, t_s, out_dir, prefix, truth)]

    def process(self, packet: FramePacket) -> FramePacket:
        renderer = self.context.renderer
        while self.pending and self.pending[0] * 1e6 < packet.t_end:
            t_s = self.pending.pop(0)
            if t_s * 1e6 < packet.t_start:
                continue
            if renderer is not None:
                frame = renderer.render(t_s * 1e6)
            elif len(packet.t) == 0:
                continue
            else:
                frame = packet.frames[int(np.argmin(np.abs(packet.t - t_s * 1e6)))]
            self._write(frame, t_s, self._prefix(), self.truth)
        return packet

    def flush(self):
        renderer = self.context.renderer
        if self.pending and renderer is not None:
            # times after the streamed stretch: the drive is defined there too
            for t_s in self.pending:
                if t_s <= renderer.max_time_s:
                    self._write(renderer.render(t_s * 1e6), t_s, self._prefix(), self.truth)
            self.pending = []
        if self.params.scenarios and not self.others_done:
            for name in self.params.scenarios:
                other, truth = renderer.with_scenario(name)
                for t_s in self.params.times_s:
                    if t_s > other.duration_s:
                        raise ConfigError(f"scene_preview: time {t_s} s lies beyond the "
                                          f"{other.duration_s:.3g} s drive of {name!r}")
                    self._write(other.render(t_s * 1e6), t_s, name, truth)
            self.others_done = True
        self.context.metrics.setdefault("scene_preview", {})["files"] = len(self.written)
        return None
