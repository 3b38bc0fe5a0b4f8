"""``frame_flow``: dense optical flow between consecutive frames (OpenCV), as flow events.

The frame baseline's flow stage: what a user of a frame camera would run. Needs OpenCV
(``pip install 'evchain[frames]'``). See ``docs/explanation/frames.md``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket, FramePacket, Geometry
from evchain.errors import ConfigError, DataError

DIS_PRESETS = ("ultrafast", "fast", "medium")


def import_cv2():
    """OpenCV, or a ConfigError saying how to install it."""
    try:
        import cv2
    except ImportError:
        raise ConfigError("frame_flow needs OpenCV: pip install 'evchain[frames]' "
                          "(opencv-python-headless)", key="frame_flow") from None
    return cv2


class FrameFlow(Filter):
    """Full optical flow between consecutive frames (DIS or Farnebäck), as flow events on a grid.

    For each frame after the first, the flow from it back to the previous frame (with
    ``baseline_ms``: the latest one at least that much older) is computed on
    the frames scaled to 8 bit (``255 * value``, clipped: frames as fractions of full scale, or
    linear intensity with white at 1) and negated, so each vector sits at its pixel in the
    later frame; divided by the frames' time difference it is in px/s. One flow event per grid
    point (every ``grid_px`` pixels, ``border_px`` from the edges) whose image gradient in the
    later frame reaches ``min_gradient`` (full scale per px; 0: every grid point), at the later
    frame's time ``t`` (for ``aps`` frames: when its exposure ended), polarity +1. The flow is
    full flow, not normal flow. OpenCV runs on ``threads`` threads (1: reproducible, and the
    chain's CPU time per stage sees all of it).
    """

    name = "frame_flow"
    consumes = FramePacket
    produces = FlowPacket

    class Params(FilterParams):
        method: Literal["dis", "farneback"] = Field(
            "dis", description="dis: dense inverse search (Kroeger et al. 2016); farneback: "
            "polynomial expansion (Farnebäck 2003)")
        grid_px: int = Field(4, ge=1, le=64, description="one flow event every this many "
                             "pixels in x and y")
        border_px: int = Field(4, ge=0, description="no flow events this close to the "
                               "image's edges")
        min_gradient: float = Field(0.0, ge=0, description="only where the later frame's "
                                    "gradient magnitude (central differences, full scale per "
                                    "px) reaches this; 0: everywhere")
        baseline_ms: float = Field(0.0, ge=0, description="flow from the latest frame at "
                                   "least this much older (0: the previous frame): a longer "
                                   "baseline measures slow motion more precisely, and later")
        threads: int = Field(1, ge=1, le=64, description="OpenCV threads")
        dis_preset: Literal["ultrafast", "fast", "medium"] = Field(
            "medium", description="DIS preset; the dis_* parameters below override it")
        dis_patch_size_px: int | None = Field(None, ge=2, description="DIS patch size")
        dis_patch_stride_px: int | None = Field(None, ge=1, description="DIS patch stride")
        dis_finest_scale: int | None = Field(None, ge=0, description="finest pyramid level "
                                             "computed (0: full resolution)")
        dis_gradient_descent_iterations: int | None = Field(None, ge=1, description="DIS "
                                                            "gradient descent iterations")
        dis_variational_refinement_iterations: int | None = Field(
            None, ge=0, description="DIS variational refinement iterations (0: none)")
        farneback_pyr_scale: float = Field(0.5, gt=0, lt=1, description="pyramid scale")
        farneback_levels: int = Field(3, ge=1, description="pyramid levels")
        farneback_window_px: int = Field(15, ge=3, description="averaging window")
        farneback_iterations: int = Field(3, ge=1, description="iterations per level")
        farneback_poly_n: int = Field(5, ge=3, description="pixel neighbourhood of the "
                                      "polynomial expansion")
        farneback_poly_sigma: float = Field(1.2, gt=0, description="Gaussian sigma of the "
                                            "polynomial expansion")

    def setup(self, params, context) -> None:
        self._cv2 = import_cv2()
        super().setup(params, context)

    def reset(self) -> None:
        self._geometry: Geometry | None = None
        self._past: list[tuple[int, np.ndarray]] = []   # earlier frames (t, 8-bit image)
        self._dis = None
        self._grid = None

    def _init(self, geometry: Geometry) -> None:
        cv2, p = self._cv2, self.params
        cv2.setNumThreads(p.threads)
        self._geometry = geometry
        b, s = p.border_px, p.grid_px
        gy, gx = np.mgrid[b:geometry.height - b:s, b:geometry.width - b:s]
        self._grid = (gy.ravel(), gx.ravel())
        if p.method == "dis":
            preset = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                      "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                      "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}[p.dis_preset]
            dis = cv2.DISOpticalFlow_create(preset)
            for value, setter in ((p.dis_patch_size_px, dis.setPatchSize),
                                  (p.dis_patch_stride_px, dis.setPatchStride),
                                  (p.dis_finest_scale, dis.setFinestScale),
                                  (p.dis_gradient_descent_iterations,
                                   dis.setGradientDescentIterations),
                                  (p.dis_variational_refinement_iterations,
                                   dis.setVariationalRefinementIterations)):
                if value is not None:
                    setter(value)
            self._dis = dis

    def _flow(self, later: np.ndarray, earlier: np.ndarray) -> np.ndarray:
        """Displacement (px) of each pixel of ``later`` since ``earlier``, [H, W, 2]."""
        cv2, p = self._cv2, self.params
        if p.method == "dis":
            back = self._dis.calc(later, earlier, None)
        else:
            back = cv2.calcOpticalFlowFarneback(
                later, earlier, None, p.farneback_pyr_scale, p.farneback_levels,
                p.farneback_window_px, p.farneback_iterations, p.farneback_poly_n,
                p.farneback_poly_sigma, 0)
        return -back

    def process(self, packet: FramePacket) -> FlowPacket:
        if self._geometry is None:
            self._init(packet.geometry)
        elif packet.geometry != self._geometry:
            raise DataError(f"frame_flow: sensor geometry changed from {self._geometry} to "
                            f"{packet.geometry}")
        cols: dict[str, list[np.ndarray]] = {k: [] for k in ("x", "y", "t", "vx", "vy")}
        for t, frame in zip(packet.t.tolist(), packet.frames, strict=True):
            img = np.clip(np.rint(frame * 255.0), 0, 255).astype(np.uint8)
            base = self._baseline(int(t))
            if base is not None:
                t0, prev = base
                self._emit(cols, int(t), (t - t0) * 1e-6, img, prev, frame)
            self._past.append((int(t), img))
        n = sum(len(c) for c in cols["x"])
        out = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in cols.items()}
        return FlowPacket(geometry=packet.geometry, t_start=packet.t_start, t_end=packet.t_end,
                          series=packet.series, x=out["x"].astype(np.uint16),
                          y=out["y"].astype(np.uint16), t=out["t"].astype(np.int64),
                          p=np.ones(n, np.int8), vx=out["vx"].astype(np.float32),
                          vy=out["vy"].astype(np.float32))

    def _baseline(self, t: int) -> tuple[int, np.ndarray] | None:
        """The latest earlier frame at least ``baseline_ms`` before ``t`` (older ones are
        dropped), or None."""
        reach = t - int(round(self.params.baseline_ms * 1000))
        usable = [i for i, (tp, _) in enumerate(self._past) if tp <= reach]
        if not usable:
            return None
        del self._past[:usable[-1]]
        return self._past[0]

    def _emit(self, cols, t: int, dt_s: float, img: np.ndarray, prev: np.ndarray,
              frame: np.ndarray) -> None:
        p = self.params
        gy, gx = self._grid
        src = img if p.method == "dis" else img.astype(np.float32)
        old = prev if p.method == "dis" else prev.astype(np.float32)
        d = self._flow(src, old)
        vx = d[gy, gx, 0] / dt_s
        vy = d[gy, gx, 1] / dt_s
        keep = np.isfinite(vx) & np.isfinite(vy)
        if p.min_gradient > 0:
            h, w = frame.shape
            f = frame.astype(np.float64, copy=False)
            ddx = (f[gy, np.minimum(gx + 1, w - 1)] - f[gy, np.maximum(gx - 1, 0)]) / 2
            ddy = (f[np.minimum(gy + 1, h - 1), gx] - f[np.maximum(gy - 1, 0), gx]) / 2
            keep &= np.hypot(ddx, ddy) >= p.min_gradient
        cols["x"].append(gx[keep])
        cols["y"].append(gy[keep])
        cols["t"].append(np.full(int(keep.sum()), t, np.int64))
        cols["vx"].append(vx[keep])
        cols["vy"].append(vy[keep])
