"""Sink ``flow_image``: PNG pictures of flow events, direction as hue (thesis Fig. 4.6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field, model_validator

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket
from evchain.errors import ConfigError


class FlowImage(Filter):
    """PNG of flow events over a time window, direction as hue (HSV colour wheel), at the end.

    One picture of ``t_window_us`` (default: the whole stream), or one per entry of
    ``times_us`` showing the ``duration_us`` before that time (files ``NAME_<t>us.png``). Each
    pixel shows its mean flow direction; sampled arrows show direction and relative speed, and
    a colour wheel in the corner is the legend. Files are
    written atomically at the end of the stream; ``save_npz`` also keeps the flow events of the
    windows, which :func:`evchain.report.flow_image.flow_image_from_file` renders again.
    """

    name = "flow_image"
    consumes = FlowPacket
    produces = None
    output_paths = ("path", "save_npz")

    class Params(FilterParams):
        path: str = Field("flow.png", description="PNG file (relative to the output folder)")
        t_window_us: tuple[int, int] | None = Field(None, description=(
            "[start, end) of the flow events shown, µs; default: the whole stream"))
        times_us: list[int] | None = Field(None, description=(
            "instead of t_window_us: one picture per time, of the duration_us before it"))
        duration_us: int = Field(100_000, gt=0, description="window of each times_us picture")
        scale: int = Field(2, ge=1, le=16, description="pixel magnification")
        wheel: bool = Field(True, description="draw the colour-wheel legend")
        arrows_every_px: int = Field(16, ge=0, description="spacing of the sampled flow "
                                     "arrows in output pixels (0: none)")
        save_npz: str | None = Field(None, description=(
            "also save the flow events of the windows (x, y, t, vx, vy, width, height) here"))

        @model_validator(mode="after")
        def _one_kind(self):
            if self.t_window_us is not None and self.times_us is not None:
                raise ValueError("give t_window_us or times_us, not both")
            if self.t_window_us is not None and self.t_window_us[1] <= self.t_window_us[0]:
                raise ValueError(f"t_window_us must be [start, end) with end > start, got "
                                 f"{list(self.t_window_us)}")
            if not self.path.lower().endswith(".png"):
                raise ValueError(f"path must end in .png, got {self.path!r}")
            return self

    @classmethod
    def output_files(cls, params) -> list[str]:
        """The PNG(s) (one per time of ``times_us``) and the ``save_npz`` file."""
        files = [params.path]
        if params.times_us is not None:
            p = Path(params.path)
            files = [str(p.with_name(f"{p.stem}_{t}us{p.suffix}")) for t in params.times_us]
        return files + ([params.save_npz] if params.save_npz else [])

    def _windows(self) -> list[tuple[Path, int | None, int | None]]:
        q = self.params
        path = self.context.output_path(q.path)
        if q.times_us is not None:
            return [(path.with_name(f"{path.stem}_{t}us{path.suffix}"), t - q.duration_us, t)
                    for t in q.times_us]
        if q.t_window_us is not None:
            return [(path, *q.t_window_us)]
        return [(path, None, None)]

    def reset(self) -> None:
        self._acc = None
        self._kept: list[FlowPacket] = []

    def process(self, packet: FlowPacket) -> FlowPacket:
        from evchain.report.flow_image import FlowAccumulator

        g = packet.geometry
        if self._acc is None:
            self._acc = [(p, FlowAccumulator(g.width, g.height, a, b))
                         for p, a, b in self._windows()]
        if len(packet):
            for _, acc in self._acc:
                acc.add(packet.x, packet.y, packet.t, packet.vx, packet.vy)
            if self.params.save_npz:
                keep = np.zeros(len(packet), bool)
                for _, acc in self._acc:
                    k = np.ones(len(packet), bool)
                    if acc.t0 is not None:
                        k &= packet.t >= acc.t0
                    if acc.t1 is not None:
                        k &= packet.t < acc.t1
                    keep |= k
                if keep.any():
                    self._kept.append(packet.select(keep))
        return packet

    def flush(self) -> FlowPacket | None:
        from evchain.io.atomic import atomic_write_bytes
        from evchain.report.flow_image import png_bytes

        if self._acc is None:
            g = self.context.geometry
            if g is None:
                raise ConfigError("flow_image: no packets and no sensor geometry to draw")
            from evchain.report.flow_image import FlowAccumulator
            self._acc = [(p, FlowAccumulator(g.width, g.height, a, b))
                         for p, a, b in self._windows()]
        for path, acc in self._acc:
            atomic_write_bytes(path, png_bytes(acc.image(self.params.scale, self.params.wheel,
                                                         self.params.arrows_every_px)))
        if self.params.save_npz:
            import io

            cols = {c: np.concatenate([getattr(p, c) for p in self._kept])
                    if self._kept else np.zeros(0, d)
                    for c, d in (("x", np.uint16), ("y", np.uint16), ("t", np.int64),
                                 ("vx", np.float32), ("vy", np.float32))}
            buf = io.BytesIO()
            np.savez(buf, **cols, width=self._acc[0][1].width, height=self._acc[0][1].height)
            atomic_write_bytes(self.context.output_path(self.params.save_npz), buf.getvalue())
        return None
