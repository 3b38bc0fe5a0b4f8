"""Source ``scene``: the built-in driving-scene simulator (thesis 4.2 scenarios, exact truth)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from pydantic import Field, model_validator

from evchain.core.filter import Filter
from evchain.core.packets import FramePacket
from evchain.core.series import IMU
from evchain.core.truth import (
    DepthTruth,
    FlowTruth,
    FoeTruth,
    ObjectTruth,
    RotationTruth,
    TtcTruth,
)
from evchain.sim.config import ImuParams, SceneConfig


class SceneSource(Filter):
    """Renders the simulated drive as frames at adaptively chosen times, with exact ground truth.

    Frames are emitted so that no pixel moves more than ``max_motion_px`` between two frames
    (from the exact motion field at the earlier frame), bounded by ``dt_min_us``/``dt_max_us``;
    ``dt_us`` fixes the step instead (thesis Table 4.4: 20 or 40 µs). ``band_rows`` renders
    each band of rows only at its own step and fills the frames between by interpolation
    (:mod:`evchain.sim.bands`). Packets cover
    ``packet_us`` slices (shorter when ``max_frames_per_packet`` is reached). Sets
    ``context.geometry`` (with f, cx, cy), ``context.truth`` (flow, FOE, camera rotation, TTC,
    depth, object ids) and ``context.renderer`` (frames at any time, for picture sinks). With
    ``imu_rate_hz`` the packets carry the camera's simulated IMU as the series ``imu`` (true
    gyro and accelerometer in the camera's axes, with optional bias and seeded noise;
    :mod:`evchain.sim.imu`), as a DAVIS recording does.
    """

    name = "scene"
    consumes = None
    produces = FramePacket
    adds_series = (IMU,)
    provides_truth = (FlowTruth, FoeTruth, RotationTruth, TtcTruth, DepthTruth,
                      ObjectTruth)

    class Params(SceneConfig, ImuParams):
        packet_us: int = Field(10_000, ge=1, le=10_000_000, description="slice per packet, µs")
        max_motion_px: float = Field(
            0.5, gt=0, le=10, description="largest image motion of any pixel between frames")
        dt_min_us: int = Field(5, ge=1, description="smallest adaptive frame interval, µs")
        dt_max_us: int = Field(10_000, ge=1, description="largest adaptive frame interval, µs")
        dt_us: int | None = Field(None, ge=1, description="fixed frame interval (no adaptation)")
        band_rows: int = Field(0, ge=0, le=8192, description=(
            "rows per band rendered only at its own step (max_motion_px over 1.5 times the "
            "band's fastest pixel speed; in the frames between, the band is the straight line "
            "between its renders): a fraction of the rows rendered where the image moves "
            "slowly, at the cost of events that differ from whole frames' (changes faster than "
            "a band's step are smoothed or lost; docs/explanation/scene.md) and one packet "
            "more of frame memory; 0 (or dt_us): every frame rendered whole"))
        max_frames_per_packet: int = Field(64, ge=1, le=100_000,
                                           description="bound on memory per packet")
        # threads != 1 also renders packets ahead in a background thread (_render_ahead)
        threads: int = Field(
            1, ge=0, le=1024, description="render threads (frames ahead at a steady step, "
            "else rows in parallel; same frames); 0: all cores")

        @model_validator(mode="after")
        def _check_dt(self):
            if self.dt_min_us > self.dt_max_us:
                raise ValueError(f"dt_min_us {self.dt_min_us} exceeds dt_max_us {self.dt_max_us}")
            return self

    @classmethod
    def series_added(cls, params):
        """``imu`` when ``imu_rate_hz`` > 0."""
        return (IMU,) if params.imu_rate_hz > 0 else ()

    def setup(self, params, context) -> None:
        from evchain.kernels.scene_bands import StepRule
        from evchain.sim.drive import Scene
        from evchain.sim.renderer import SceneRenderer
        from evchain.sim.truth import SceneTruth

        check_memory(params)
        #: the adaptive step's rule (``next_dt_us``; the row bands' schedule)
        self.step_rule = StepRule(float(params.max_motion_px), int(params.dt_min_us),
                                  int(params.dt_max_us))
        self.scene = Scene(params, threads=params.threads)
        self.truth = SceneTruth(self.scene)
        self.duration_us = int(round(self.scene.duration_s * 1e6))
        context.geometry = self.scene.geometry
        context.truth = self.truth
        context.renderer = SceneRenderer(self.scene)
        super().setup(params, context)

    def reset(self) -> None:
        self.frames_emitted = 0

    @staticmethod
    def frame_memory_bytes(params) -> int:
        """Peak bytes of the frames the source holds: a packet's frames twice (rendered one by
        one, then stacked; float32), for four packets when rendering ahead (two queued, one
        being rendered, one being consumed)."""
        packets = 1 if params.threads == 1 else 4
        if params.band_rows and params.dt_us is None:
            packets += 1        # the frames waiting for their bands' next renders
        return params.width * params.height * 4 * 2 * params.max_frames_per_packet * packets

    def time_span_us(self) -> tuple[int, int]:
        return (0, self.duration_us)

    def next_dt_us(self, vmax_pxs: float) -> int:
        """Frame interval after a frame whose fastest sample moves at ``vmax_pxs``."""
        if self.params.dt_us is not None:
            return self.params.dt_us
        from evchain.kernels.scene_bands import step_us

        return int(step_us(self.step_rule, float(vmax_pxs)))

    def packets(self) -> Iterator[FramePacket]:
        from evchain.sim.imu import noise_key

        self._imu_key = noise_key(self.context, self.id)
        if self.params.threads == 1:
            yield from self._render_packets()
        else:
            yield from self._render_ahead()

    def _render_ahead(self) -> Iterator[FramePacket]:
        """The same packets, rendered by a background thread up to two packets ahead, so
        that the next stages (e.g. the emulator) run while the next frames render (the render
        kernels release the GIL). Same packets in the same order as without."""
        import queue
        import threading

        q: queue.Queue = queue.Queue(maxsize=2)
        stop = threading.Event()

        def put(item) -> bool:
            while not stop.is_set():
                try:
                    q.put(item, timeout=0.05)
                    return True
                except queue.Full:
                    continue
            return False

        def work() -> None:
            try:
                for pkt in self._render_packets():
                    if not put(("packet", pkt)):
                        return
                put(("end", None))
            except BaseException as exc:     # handed to the consuming thread
                put(("error", exc))

        worker = threading.Thread(target=work, name="scene-render-ahead", daemon=True)
        worker.start()
        try:
            while True:
                kind, value = q.get()
                if kind == "packet":
                    yield value
                elif kind == "error":
                    raise value
                else:
                    return
        finally:
            stop.set()
            worker.join()

    def _render_packets(self) -> Iterator[FramePacket]:
        p = self.params
        geom = self.context.geometry
        end = self.duration_us
        t = 0           # time of the next frame
        t_start = 0
        dts: list[int] = []
        bands = None
        if p.band_rows and p.dt_us is None:
            from evchain.sim.bands import BandFrames

            bands = BandFrames(self.scene, p.band_rows, p.max_frames_per_packet)
            seq = bands.frames(0, end, self.step_rule)
        else:
            def step(vmax: float) -> int:
                dts.append(self.next_dt_us(vmax))
                return dts[-1]

            seq = ((t_f, frame, dts[-1]) for t_f, frame, _ in self.scene.frames(0, end, step))
        while t_start < end:
            boundary = min(t_start - t_start % p.packet_us + p.packet_us, end)
            frames, times = [], []
            while t < boundary and len(frames) < p.max_frames_per_packet:
                t_f, frame, dt = next(seq)          # the frame at t (a new array)
                if t_f != t:
                    raise RuntimeError(f"scene frame at {t_f} µs, expected {t} µs")
                frames.append(frame)
                times.append(t)
                if bands is not None:
                    dts.append(dt)
                t += dt
            t_end = boundary if t >= boundary else t
            stack = (np.stack(frames) if frames
                     else np.zeros((0, geom.height, geom.width), np.float32))
            self.frames_emitted += len(times)
            packet = FramePacket(geometry=geom, t_start=t_start, t_end=t_end, frames=stack,
                                 t=np.array(times, np.int64))
            imu = self.params.imu_between(self.scene, t_start, t_end, self._imu_key)
            yield packet if imu is None else packet.with_series(IMU.name, imu)
            t_start = t_end
        metrics = {
            "frames": self.frames_emitted,
            "duration_s": end * 1e-6,
            "mean_dt_us": float(np.mean(dts)) if dts else None,
            "min_dt_us": int(np.min(dts)) if dts else None,
            "scenario": p.scenario,
            "speed_mps": p.speed_mps,
            "f_px": geom.f,
        }
        if bands is not None:     # share of the emitted frames' pixel rows that were rendered
            metrics["rendered_share"] = (bands.rows_rendered / (bands.frames_emitted
                                                                * geom.height)
                                         if bands.frames_emitted else 1.0)
        self.context.metrics["scene"] = metrics


def check_memory(params) -> None:
    """Refuse a camera whose frames alone would not fit in the memory available (before any
    rendering, instead of running out of memory minutes later)."""
    from evchain.errors import ConfigError
    from evchain.machine import available_memory_bytes

    need = SceneSource.frame_memory_bytes(params)
    have = available_memory_bytes()
    if have is not None and need > have:
        ahead = "" if params.threads == 1 else ", x4 for the packets rendered ahead (threads)"
        raise ConfigError(
            f"a {params.width}x{params.height} camera needs about {need / 2**30:.1f} GiB for the "
            f"frames of one packet (max_frames_per_packet {params.max_frames_per_packet} "
            f"float32 frames, rendered and stacked{ahead}), more than the "
            f"{have / 2**30:.1f} GiB of memory available; lower width and height, or "
            "max_frames_per_packet", key="scene.width")
