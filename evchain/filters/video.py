"""Sink ``video``: a movie of the stream (events, flow by direction, FOE and TTC overlays)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket
from evchain.core.series import FOE, TTC, TTC_CLUSTERS
from evchain.core.truth import FoeTruth
from evchain.errors import ConfigError
from evchain.io.atomic import AtomicFile
from evchain.report.movie import MovieWriter, gif_delay_ms
from evchain.report.video_frame import compose

#: the latest tick's TTC clusters stay on screen this long (µs) when no newer tick comes
CLUSTERS_SHOWN_US = 100_000


class Video(Filter):
    """Write a video of the stream: one frame per ``frame_us`` of events (flow events coloured by
    direction). Overlays (``overlay: all``): the estimated FOE (yellow, from the ``foe`` series)
    and the true FOE (red, from the ground truth) with a legend, the stream time and the
    obstacle's TTC (from the ``ttc`` series), the TTC clusters of the latest tick (from
    ``ttc_clusters``, for up to 100 ms) with their TTC as labels that never overlap, and on flow
    frames sampled flow arrows and the colour wheel of directions (see
    :mod:`evchain.report.video_frame`).

    ``.gif`` needs nothing extra; ``.mp4`` needs ``pip install 'evchain[video]'``. Frames are
    taken at fixed times, so packet cuts do not change the video. A GIF's frame delay is whole
    hundredths of a second (``fps`` at most 50; 30 fps plays as 33.3, with a warning); an MP4
    plays at ``fps`` exactly (see :mod:`evchain.report.movie`).
    """

    name = "video"
    consumes = EventPacket
    optional_series = (FOE, TTC, TTC_CLUSTERS)
    uses_truth = (FoeTruth,)
    output_paths = ("path",)

    class Params(FilterParams):
        path: str = Field("events.gif", description="output file (.gif or .mp4), in the run folder")
        frame_us: int = Field(10_000, ge=100, description="stream time shown by one video frame")
        fps: float = Field(25.0, gt=0, le=240, description="playback frames per second")
        scale: int = Field(2, ge=1, le=8, description="pixel magnification")
        max_frames: int = Field(2000, ge=1, description="stop adding frames after this many")
        overlay: Literal["all", "none"] = Field(
            "all", description="draw FOE, TTC and flow overlays (markers, legend, labels, "
            "arrows, colour wheel)")
        arrows_every_px: int = Field(16, ge=0, description="spacing of the sampled flow "
                                     "arrows in output pixels (0: none)")

    def setup(self, params, context):
        suffix = Path(params.path).suffix.lower()
        if suffix not in (".gif", ".mp4"):
            raise ConfigError(f"video path must end in .gif or .mp4, got {params.path!r}",
                              key="video.path")
        self.kind = suffix[1:]
        if self.kind == "gif":
            delay_ms = gif_delay_ms(params.fps)
            if abs(delay_ms - 1000.0 / params.fps) > 1e-6:
                context.warn(f"video: {params.path}: a GIF frame lasts whole hundredths of a "
                             f"second; fps {params.fps:g} plays as {1000 / delay_ms:.4g} "
                             f"({delay_ms} ms per frame)")
        super().setup(params, context)

    def reset(self):
        self.close()
        self.out = AtomicFile.reserve(self.context.output_path(self.params.path))
        self.writer = None
        self.frame_start = None
        self.pending: list[EventPacket] = []
        self.foe = (np.nan, np.nan)
        self.ttc_text = ""
        self.clusters = None
        self.obstacle = None
        self.frames = 0

    def _open(self) -> MovieWriter:
        return MovieWriter(self.out.tmp, self.kind, self.params.fps)

    def process(self, packet: EventPacket) -> EventPacket:
        if self.frame_start is None:
            self.frame_start = packet.t_start - packet.t_start % self.params.frame_us
        self.pending.append(packet)
        while packet.t_end >= self.frame_start + self.params.frame_us:
            self._emit(self.frame_start + self.params.frame_us)
        return packet

    def _emit(self, t_end: int) -> None:
        whole = type(self.pending[0]).concat(self.pending)
        keep = whole.t < t_end
        shown = whole.select(keep)
        series = {k: v[v["t"] < t_end] for k, v in whole.series.items()}
        self.pending = [whole.select(~keep).replace(
            t_start=t_end, series={k: v[v["t"] >= t_end] for k, v in whole.series.items()})]
        self.frame_start = t_end
        if self.frames >= self.params.max_frames:
            return
        foe, ttc = series.get(FOE.name), series.get(TTC.name)
        clusters = series.get(TTC_CLUSTERS.name)
        if foe is not None and len(foe):
            self.foe = (foe["x"][-1], foe["y"][-1])
        if ttc is not None and len(ttc):
            self.ttc_text = f"TTC {ttc['tau_s'][-1]:.2f} s"
            self.obstacle = int(ttc["cluster"][-1])
        if clusters is not None and len(clusters):
            self.clusters = clusters[clusters["t"] == clusters["t"][-1]]
        if self.clusters is not None and t_end - self.clusters["t"][0] > CLUSTERS_SHOWN_US:
            self.clusters = None  # no live cluster lately
        foe_true = None
        if isinstance(self.truth, FoeTruth):
            tx, ty = self.truth.foe(np.array([t_end], np.float64))
            foe_true = (float(tx[0]), float(ty[0]))
        img, _ = compose(shown, self.params.scale, self.params.overlay == "all", self.foe,
                         foe_true, f"{t_end / 1e6:8.3f} s  {self.ttc_text}", self.clusters,
                         self.obstacle, self.params.arrows_every_px)
        if self.writer is None:
            self.writer = self._open()
        self.writer.append(img)
        self.frames += 1

    def flush(self):
        if self.pending and len(self.pending[0]):
            self._emit(int(self.pending[0].t[-1]) + 1)
        if self.writer is None:
            self.writer = self._open()  # an empty stream still gives a (one-frame) valid file
            g = self.context.geometry
            self.writer.append(np.zeros((g.height * self.params.scale,
                                              g.width * self.params.scale, 3), np.uint8))
        self.writer.close()
        self.writer = None
        self.out.commit()
        return None

    def close(self):
        writer = getattr(self, "writer", None)
        if writer is not None:
            writer.close()
            self.writer = None
            self.out.abort()
