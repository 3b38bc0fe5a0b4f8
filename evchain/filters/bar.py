"""Source ``bar``: the thesis's moving-bar validation stimulus (section 4.1), rendered exactly.

See :mod:`evchain.sim.bar` for the profiles and the ground truth.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FramePacket, Geometry
from evchain.core.truth import FlowTruth


class BarSource(Filter):
    """Moving white bar over black (thesis 4.1): frames with exact ground truth and crossing times.

    A full-height bar moves right at ``speed_pxs``; edges sharp (exact pixel-area coverage) or
    gradual (linear ramp, logistic sigmoid or Gaussian-blurred erf of ``edge_width_px``). Frames
    at ``t_start_us + k * dt_us``. Ground truth: flow (bar velocity on the bar, 0 elsewhere),
    FOE and TTC (undefined for a translation: NaN) and ``crossing_times(...)`` of every log
    level for the emulator.
    """

    name = "bar"
    consumes = None
    produces = FramePacket
    provides_truth = (FlowTruth,)

    class Params(FilterParams):
        width: int = Field(64, ge=1, le=4096, description="sensor width in pixels")
        height: int = Field(48, ge=1, le=4096, description="sensor height in pixels")
        bar_width_px: float = Field(16.0, gt=0, description="bar width between edge centres")
        speed_pxs: float = Field(200.0, gt=0, description="speed to the right, px/s")
        x0_px: float = Field(0.0, description="leading edge position at t = 0 (pixel coords)")
        edge: Literal["sharp", "linear", "sigmoid", "erf"] = Field(
            "erf", description="edge profile")
        edge_width_px: float = Field(2.0, gt=0, description="ramp width (linear, sigmoid) or "
                                     "Gaussian sigma (erf); unused for sharp")
        supersample: int = Field(1, ge=1, le=64, description="samples across each pixel for "
                                 "gradual edges (sharp edges use the exact pixel area)")
        intensity_bar: float = Field(1.0, ge=0, description="linear intensity of the bar")
        intensity_background: float = Field(0.0, ge=0, description="linear intensity of the "
                                            "background")
        t_start_us: int = Field(0, ge=0, description="time of the first frame")
        duration_us: int = Field(200_000, ge=1, description="frames at t < t_start + duration")
        dt_us: int = Field(1000, ge=1, description="time between frames")
        frames_per_packet: int = Field(50, ge=1, description="frames per emitted packet")

    def setup(self, params, context) -> None:
        from evchain.sim.bar import Bar, BarTruth

        p = params
        self.bar = Bar(width=p.width, height=p.height, bar_width_px=p.bar_width_px,
                       speed_pxs=p.speed_pxs, x0_px=p.x0_px, edge=p.edge,
                       edge_width_px=p.edge_width_px, supersample=p.supersample,
                       intensity_bar=p.intensity_bar,
                       intensity_background=p.intensity_background)
        self.truth = BarTruth(self.bar)
        context.geometry = Geometry(p.width, p.height)
        context.truth = self.truth
        super().setup(params, context)

    def frame_times(self) -> np.ndarray:
        p = self.params
        return np.arange(p.t_start_us, p.t_start_us + p.duration_us, p.dt_us, dtype=np.int64)

    def time_span_us(self) -> tuple[int, int]:
        p = self.params
        return p.t_start_us, p.t_start_us + p.duration_us

    def packets(self) -> Iterator[FramePacket]:
        p = self.params
        t_all = self.frame_times()
        geometry = self.context.geometry
        end = p.t_start_us + p.duration_us
        for i in range(0, len(t_all), p.frames_per_packet):
            t = t_all[i:i + p.frames_per_packet]
            nxt = i + p.frames_per_packet
            t_end = int(t_all[nxt]) if nxt < len(t_all) else end
            yield FramePacket(geometry=geometry, t_start=int(t[0]), t_end=t_end,
                              frames=self.bar.render(t), t=t)
