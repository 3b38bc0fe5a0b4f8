"""A simulated drive: world + trajectory + camera, rendered at any float time.

>>> scene = Scene.from_params(scenario="open-field", width=64, height=48, duration_s=0.1)
>>> frame, vmax = scene.render(0.05)      # linear intensity [48, 64], max image speed in px/s
"""

from __future__ import annotations

import math
import os
import threading
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from evchain.sim.camera import Camera
from evchain.sim.config import SceneConfig, make_config
from evchain.sim.scenarios import build_world
from evchain.sim.world import ground_textures


class Scene:
    """Everything needed to render frames and answer ground truth for one configuration."""

    def __init__(self, cfg: SceneConfig, threads: int = 1):
        self.cfg = cfg
        self.threads = threads
        self.camera = Camera(cfg.width, cfg.height, cfg.fov_deg, cfg.supersample)
        self.world = build_world(cfg)
        self.boxes, self.box_mat, self.box_par = self.world.arrays()
        self.segs = self.world.segs
        self.ground = self.world.ground
        self.light = self.world.light
        self.tex, self.tex_inv, self.tex_off = ground_textures(int(self.ground[8]))
        self.traj = np.array([
            cfg.start_m, cfg.speed_mps, cfg.camera_height_m,
            math.radians(cfg.pitch_amplitude_deg), cfg.pitch_frequency_hz,
            cfg.pitch_shift_interval_s, cfg.pitch_decay_s, cfg.pitch_first_shift_s,
            1.0 if cfg.dynamics == "pitch" else 0.0, float(len(self.segs)),
            math.radians(cfg.pan_dps), math.radians(cfg.tilt_dps), cfg.rotation_start_s],
            np.float64)
        self.duration_s = cfg.drive_s
        #: the latest time the route supports (the drive may stop earlier)
        self.max_time_s = ((self.world.route_m - cfg.start_m) / cfg.speed_mps
                           if cfg.speed_mps > 0 else self.duration_s)
        self._pool: ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()

    @classmethod
    def from_params(cls, threads: int = 1, **values) -> Scene:
        """A scene from keyword parameters (see :class:`SceneConfig`); errors are ConfigError.
        ``threads`` > 1 (0: all) renders rows in parallel."""
        return cls(make_config(SceneConfig, **values), threads=threads)

    @property
    def geometry(self):
        return self.camera.geometry

    def state(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(position, camera-to-world rotation, camera velocity, angular velocity) at t_s;
        velocities in camera coordinates (m/s, rad/s)."""
        from evchain.kernels.scene_geometry import camera_state

        pos, rot, vc, wc = np.zeros(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3)
        camera_state(float(t_s), self.segs, self.traj, pos, rot, vc, wc)
        return pos, rot, vc, wc

    def _frame_args(self, t_s: float, out: np.ndarray, scratch: tuple) -> tuple:
        """Kernel arguments (FrameView, WorldArrays, out) of the frame at t_s (camera state and
        visible boxes written into ``scratch`` = pos, rot, vc, wc, order, minz, bbox)."""
        from evchain.kernels.scene_culling import frame_boxes
        from evchain.kernels.scene_geometry import FrameView, WorldArrays, camera_state

        cam = self.camera
        pos, rot, vc, wc, order, minz, bbox = scratch
        camera_state(float(t_s), self.segs, self.traj, pos, rot, vc, wc)
        if rot[2, 0] != 0.0:     # the row renderer relies on it; camera_state ensures it
            raise RuntimeError("scene camera must not roll")
        nvis = frame_boxes(self.boxes, pos, rot, cam.f, cam.cx, cam.cy, cam.width,
                           cam.height, order, minz, bbox)
        frame = FrameView(pos, rot, vc, wc, cam.f, cam.cx, cam.cy, cam.supersample, order[:nvis],
                          minz, bbox)
        world = WorldArrays(self.boxes, self.box_mat, self.box_par, self.segs, self.ground,
                            self.light, self.tex, self.tex_inv, self.tex_off)
        return frame, world, out

    def _scratch(self) -> tuple:
        nb = len(self.boxes)
        return (np.zeros(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3), np.zeros(nb, np.int64),
                np.zeros(nb), np.zeros((nb, 4)))

    def _pool_of(self, nt: int) -> ThreadPoolExecutor:
        with self._pool_lock:     # render() may be called from several threads
            if self._pool is None:
                self._pool = ThreadPoolExecutor(nt, thread_name_prefix="scene-render")
            return self._pool

    def render(self, t_s: float, out: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """Frame (float32 [H, W], linear intensity) at time t_s and the largest image speed
        (px/s) at that time over the first sample row of every pixel row (drives the adaptive
        time step). Thread-safe: each call has scratch of its own, so a picture sink may render
        while :meth:`frames` renders on other threads."""
        from evchain.kernels.scene_render import render, render_rows

        cam = self.camera
        if out is None:
            out = np.empty((cam.height, cam.width), np.float32)
        args = self._frame_args(t_s, out, self._scratch())
        nt = self._nthreads()
        if nt == 1:
            vmax = render(*args)
        else:      # interleaved rows on nt threads (the kernel releases the GIL)
            pool = self._pool_of(nt)
            jobs = [pool.submit(render_rows, *args, j, nt) for j in range(1, nt)]
            vmax = max([render_rows(*args, 0, nt)] + [job.result() for job in jobs])
        return self._contrast(out), float(vmax)

    def _render_alone(self, t_s: float) -> tuple[np.ndarray, float]:
        """:meth:`render` on the calling thread only, with scratch of its own (thread-safe)."""
        from evchain.kernels.scene_render import render

        cam = self.camera
        out = np.empty((cam.height, cam.width), np.float32)
        vmax = float(render(*self._frame_args(t_s, out, self._scratch())))
        return self._contrast(out), vmax

    def _contrast(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` (in place) with its log contrast scaled by ``cfg.contrast`` around mid grey
        0.5; 0 gives a uniform grey frame."""
        c = self.cfg.contrast
        if c == 0.0:
            frame.fill(0.5)
        elif c != 1.0:
            np.power(frame / np.float32(0.5), np.float32(c), out=frame)
            frame *= np.float32(0.5)
        return frame

    def _nthreads(self) -> int:
        return self.threads or (os.cpu_count() or 1)

    def frames(self, t_us: int, end_us: int, next_dt_us: Callable[[float], int]
               ) -> Iterator[tuple[int, np.ndarray, float]]:
        """(t, frame, vmax) for t = t_us, then t + next_dt_us(vmax), ... while t < end_us
        (times in integer µs; each frame a new array; next_dt_us is called before its frame
        is yielded).

        With more than one thread, frames whose time is already known render whole, one per
        thread, without a barrier between frames: when a frame's step equals the step before
        it, the next frames are started at that same step ahead of time (speculatively) and
        kept if the step is confirmed, dropped otherwise. After a changed step the next frame
        renders with its rows spread over the threads. Same frames and times as one thread."""
        nt = self._nthreads()
        if nt == 1:
            while t_us < end_us:
                frame, vmax = self.render(t_us * 1e-6)
                dt = next_dt_us(vmax)
                yield t_us, frame, vmax
                t_us += dt
            return
        pool = self._pool_of(nt)
        ahead: deque = deque()      # (t, future) at consecutive predicted times
        dt_last = None
        while t_us < end_us:
            if ahead and ahead[0][0] == t_us:
                frame, vmax = ahead.popleft()[1].result()
            else:
                _drop(ahead)       # mispredicted
                frame, vmax = self.render(t_us * 1e-6)
            dt = next_dt_us(vmax)
            if dt == dt_last:      # steady step: keep 2 nt frames queued, so that no thread
                # waits while the caller works on a frame (emulator, writer)
                t_next = ahead[-1][0] if ahead else t_us
                while len(ahead) < 2 * nt and t_next + dt < end_us:
                    t_next += dt
                    ahead.append((t_next, pool.submit(self._render_alone, t_next * 1e-6)))
            else:
                _drop(ahead)
            dt_last = dt
            yield t_us, frame, vmax
            t_us += dt

    def world_to_camera(self, points: np.ndarray, t_s: float) -> np.ndarray:
        """Camera-frame coordinates [n, 3] of world points [n, 3] at time t_s."""
        pos, rot, _, _ = self.state(t_s)
        return (np.asarray(points, float) - pos) @ rot

    def project(self, points: np.ndarray, t_s: float) -> np.ndarray:
        """Pixel coordinates [n, 2] of world points at time t_s (pinhole)."""
        return self.camera.project(self.world_to_camera(points, t_s))


def _drop(ahead: deque) -> None:
    """Forget frames rendered ahead at a step that did not hold; those not started yet are
    cancelled (running ones finish unused)."""
    for _, job in ahead:
        job.cancel()
    ahead.clear()
