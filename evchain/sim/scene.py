"""A simulated drive: world + trajectory + camera, rendered at any float time.

>>> scene = Scene.from_params(scenario="open-field", width=64, height=48, duration_s=0.1)
>>> frame, vmax = scene.render(0.05)      # linear intensity [48, 64], max image speed in px/s
"""

from __future__ import annotations

import math
import os
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
            1.0 if cfg.dynamics == "pitch" else 0.0, float(len(self.segs))], np.float64)
        self.duration_s = cfg.drive_s
        #: the latest time the route supports (the drive may stop earlier)
        self.max_time_s = ((self.world.route_m - cfg.start_m) / cfg.speed_mps
                           if cfg.speed_mps > 0 else self.duration_s)
        nb = len(self.boxes)
        self._order = np.zeros(nb, np.int64)
        self._minz = np.zeros(nb, np.float64)
        self._bbox = np.zeros((nb, 4), np.float64)
        self._pos = np.zeros(3)
        self._rot = np.zeros((3, 3))
        self._vc = np.zeros(3)
        self._wc = np.zeros(3)
        self._pool: ThreadPoolExecutor | None = None

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
        from evchain.kernels.scene import camera_state

        pos, rot, vc, wc = np.zeros(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3)
        camera_state(float(t_s), self.segs, self.traj, pos, rot, vc, wc)
        return pos, rot, vc, wc

    def render(self, t_s: float, out: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """Frame (float32 [H, W], linear intensity) at time t_s and the largest image speed
        (px/s) of any sample at that time (drives the adaptive time step)."""
        from evchain.kernels.scene import camera_state, frame_boxes, render, render_rows

        cam = self.camera
        if out is None:
            out = np.empty((cam.height, cam.width), np.float32)
        camera_state(float(t_s), self.segs, self.traj, self._pos, self._rot, self._vc, self._wc)
        if self._rot[2, 0] != 0.0:     # the row renderer relies on it; camera_state ensures it
            raise RuntimeError("scene camera must not roll")
        nvis = frame_boxes(self.boxes, self._pos, self._rot, cam.f, cam.cx, cam.cy, cam.width,
                           cam.height, self._order, self._minz, self._bbox)
        args = (self._pos, self._rot, self._vc, self._wc, cam.f, cam.cx, cam.cy,
                cam.supersample, self.boxes, self.box_mat, self.box_par, self.segs,
                self.ground, self.light, self.tex, self.tex_inv, self.tex_off,
                self._order[:nvis], self._minz, self._bbox, out)
        nt = self.threads or (os.cpu_count() or 1)
        if nt == 1:
            vmax = render(*args)
        else:      # interleaved rows on nt threads (the kernel releases the GIL)
            if self._pool is None:
                self._pool = ThreadPoolExecutor(nt - 1, thread_name_prefix="scene-render")
            jobs = [self._pool.submit(render_rows, *args, j, nt) for j in range(1, nt)]
            vmax = max([render_rows(*args, 0, nt)] + [job.result() for job in jobs])
        return out, float(vmax)

    def world_to_camera(self, points: np.ndarray, t_s: float) -> np.ndarray:
        """Camera-frame coordinates [n, 3] of world points [n, 3] at time t_s."""
        pos, rot, _, _ = self.state(t_s)
        return (np.asarray(points, float) - pos) @ rot

    def project(self, points: np.ndarray, t_s: float) -> np.ndarray:
        """Pixel coordinates [n, 2] of world points at time t_s (pinhole)."""
        return self.camera.project(self.world_to_camera(points, t_s))
