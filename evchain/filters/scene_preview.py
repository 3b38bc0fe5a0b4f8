"""Sink ``scene_preview``: PNGs of frame, depth and ground-truth flow at chosen times."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FramePacket
from evchain.errors import ConfigError


class ScenePreview(Filter):
    """Writes PNGs of the frame, depth and ground-truth flow (hue = direction) at chosen times.

    For each time in ``times_s`` it renders the frame exactly at that time when the ground-truth
    provider can (the ``scene`` source's can; times after the streamed stretch but inside the
    drive are pictured at the end), else takes the nearest frame of the packet; depth and flow
    come from the provider when it has them. ``scenarios`` additionally pictures the drive of
    other scenarios (same camera and speed, from the start of their route; ``scene`` source
    only), so one pipeline previews them all. Passes frames on unchanged.
    """

    name = "scene_preview"
    consumes = FramePacket
    produces = None
    output_paths = ("out",)

    class Params(FilterParams):
        times_s: list[float] = Field([0.0], description="times (s) to picture")
        out: str = Field("preview", description="folder (relative to the run's output)")
        scenarios: list[str] = Field([], description="also picture these scenarios at times_s")

    def setup(self, params, context) -> None:
        if any(t < 0 for t in params.times_s):
            raise ConfigError(f"scene_preview: times_s must be >= 0, got {params.times_s}")
        if params.scenarios and not hasattr(context.truth, "with_scenario"):
            raise ConfigError("scene_preview: 'scenarios' needs the 'scene' source upstream")
        super().setup(params, context)

    def reset(self) -> None:
        self.pending = sorted(set(self.params.times_s))
        self.written: list[str] = []
        self.others_done = False

    def _prefix(self) -> str:
        truth = self.context.truth
        cfg = getattr(getattr(truth, "scene", None), "cfg", None)
        return cfg.scenario if cfg is not None else "stream"

    def process(self, packet: FramePacket) -> FramePacket:
        from evchain.sim.preview import write_preview

        out_dir = self.context.output_path(self.params.out)
        truth = self.context.truth
        while self.pending and self.pending[0] * 1e6 < packet.t_end:
            t_s = self.pending.pop(0)
            if t_s * 1e6 < packet.t_start:
                continue
            frame = None
            if not hasattr(truth, "render"):
                if len(packet.t) == 0:
                    continue
                frame = packet.frames[int(np.argmin(np.abs(packet.t - t_s * 1e6)))]
            self.written += [str(p) for p in write_preview(truth, t_s, out_dir, self._prefix(),
                                                           frame=frame)]
        return packet

    def flush(self):
        truth = self.context.truth
        if self.pending and hasattr(truth, "render") and hasattr(truth, "scene"):
            # times after the streamed stretch: the drive is defined there too
            from evchain.sim.preview import write_preview

            out_dir = self.context.output_path(self.params.out)
            for t_s in self.pending:
                if t_s <= truth.scene.max_time_s:
                    self.written += [str(p) for p in write_preview(truth, t_s, out_dir,
                                                                   self._prefix())]
            self.pending = []
        if self.params.scenarios and not self.others_done:
            from evchain.sim.preview import write_preview

            out_dir = self.context.output_path(self.params.out)
            for name in self.params.scenarios:
                other = self.context.truth.with_scenario(name)
                for t_s in self.params.times_s:
                    if t_s > other.scene.duration_s:
                        raise ConfigError(f"scene_preview: time {t_s} s lies beyond the "
                                          f"{other.scene.duration_s:.3g} s drive of {name!r}")
                    self.written += [str(p) for p in write_preview(other, t_s, out_dir, name)]
            self.others_done = True
        self.context.metrics.setdefault("scene_preview", {})["files"] = len(self.written)
        return None
