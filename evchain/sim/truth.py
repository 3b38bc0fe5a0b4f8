"""Exact ground truth of a simulated drive, at any pixel position and time.

:class:`SceneTruth` implements every protocol of :mod:`evchain.core.truth` (``flow``, ``foe``,
``angular_velocity``, ``ttc``, ``depth``, ``object_id`` and ``obstacle_ids``; times in µs,
floats allowed, scalars or arrays that broadcast); it answers questions, it does not render
(the ``scene`` source's :class:`~evchain.sim.renderer.SceneRenderer` does). Depth uses the
renderer's own ray caster; flow is the motion field of the camera's translation and rotation
at that depth:

    u' = f [(-vX + x̄ vZ) / Z + ωX x̄ ȳ - ωY (1 + x̄²) + ωZ ȳ]
    v' = f [(-vY + ȳ vZ) / Z + ωX (1 + ȳ²) - ωY x̄ ȳ - ωZ x̄]

with x̄ = (x - cx)/f, ȳ = (y - cy)/f and (v, ω) the camera's velocities in camera coordinates.
Sky pixels have Z = inf and only the rotational part. All objects are static, so no object
motion enters. FOE = projection of the translational velocity (thesis eq. 3.5), NaN unless
moving forward: the heading (under pitch and in curves the flow does not vanish there, its
rotational part remains); angular velocity = ω; TTC = (obstacle - camera)·v / |v|² (thesis
eq. 3.6), NaN without an obstacle, at rest, or once passed.

Objects: ``object_id`` names the surface seen at (x, y): the index of its box in the world's
boxes (>= 0), ``OBJECT_GROUND`` (-2) or ``OBJECT_SKY`` (-1); ``obstacle_ids`` are the boxes of
the obstacle car (empty without one).
"""

from __future__ import annotations

import numpy as np

from evchain.sim.drive import Scene
from evchain.sim.world import OBJECT_GROUND, OBJECT_SKY

__all__ = ["OBJECT_GROUND", "OBJECT_SKY", "SceneTruth"]


class SceneTruth:
    """Ground-truth provider of a :class:`~evchain.sim.drive.Scene`: a ``FlowTruth``,
    ``FoeTruth``, ``RotationTruth``, ``TtcTruth``, ``DepthTruth`` and ``ObjectTruth``."""

    def __init__(self, scene: Scene):
        self._scene = scene
        cam = scene.camera
        self.f, self.cx, self.cy = cam.f, cam.cx, cam.cy
        self.obstacle_ids: np.ndarray = scene.world.obstacle_ids   # box indices of the car

    # -- per pixel ------------------------------------------------------------------------
    def _query(self, x, y, t_us):
        from evchain.kernels.scene_truth import truth_query

        x, y, t = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                      np.asarray(t_us, np.float64))
        shape = x.shape
        xf = np.ascontiguousarray(x.ravel())
        yf = np.ascontiguousarray(y.ravel())
        tf = np.ascontiguousarray(t.ravel()) * 1e-6
        s = self._scene
        depth, vx, vy, obj = truth_query(xf, yf, tf, self.f, self.cx, self.cy, s.boxes, s.segs,
                                         s.traj)
        return depth.reshape(shape), vx.reshape(shape), vy.reshape(shape), obj.reshape(shape)

    def depth(self, x, y, t_us) -> np.ndarray:
        """Depth Z (m, along the optical axis) of the surface seen at (x, y); inf for sky."""
        return self._query(x, y, t_us)[0]

    def flow(self, x, y, t_us) -> tuple[np.ndarray, np.ndarray]:
        """Motion field (vx, vy) in px/s at (x, y) and t_us."""
        _, vx, vy, _ = self._query(x, y, t_us)
        return vx, vy

    def depth_and_flow(self, x, y, t_us):
        """(depth, vx, vy) in one pass."""
        return self._query(x, y, t_us)[:3]

    def object_id(self, x, y, t_us) -> np.ndarray:
        """Id (int64) of the surface seen at (x, y) at t_us (>= 0): the index of its box (see
        ``obstacle_ids``), ``OBJECT_GROUND`` or ``OBJECT_SKY``."""
        return self._query(x, y, t_us)[3]

    # -- per time ----------------------------------------------------------------------------
    def _states(self, t_us):
        from evchain.kernels.scene_geometry import camera_states

        t = np.asarray(t_us, np.float64)
        tf = np.ascontiguousarray(t.ravel()) * 1e-6
        n = tf.size
        pos, rot, vc, wc = np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 3))
        if n:
            camera_states(tf, self._scene.segs, self._scene.traj, pos, rot, vc, wc)
        return t.shape, pos, rot, vc, wc

    def velocity(self, t_us):
        """Camera velocity and angular velocity in camera coordinates, [..., 3] each."""
        shape, _, _, vc, wc = self._states(t_us)
        return vc.reshape(*shape, 3), wc.reshape(*shape, 3)

    def angular_velocity(self, t_us) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The camera's angular velocity (wx, wy, wz) in rad/s about its own axes."""
        shape, _, _, _, wc = self._states(t_us)
        return _shaped(wc[:, 0], shape), _shaped(wc[:, 1], shape), _shaped(wc[:, 2], shape)

    def foe(self, t_us) -> tuple[np.ndarray, np.ndarray]:
        """Focus of expansion (x, y) in pixels (thesis eq. 3.5): the heading, the projection of
        the translational velocity, also while the camera rotates; NaN unless moving forward."""
        shape, _, _, vc, _ = self._states(t_us)
        fwd = vc[:, 2] > 1e-9
        vz = np.where(fwd, vc[:, 2], 1.0)
        x = np.where(fwd, self.f * vc[:, 0] / vz + self.cx, np.nan)
        y = np.where(fwd, self.f * vc[:, 1] / vz + self.cy, np.nan)
        return _shaped(x, shape), _shaped(y, shape)

    def ttc(self, t_us) -> np.ndarray:
        """Time to contact with the obstacle in s (thesis eq. 3.6); NaN when undefined."""
        shape, pos, rot, vc, _ = self._states(t_us)
        target = self._scene.world.obstacle_rear
        if target is None:
            return _shaped(np.full(len(pos), np.nan), shape)
        vw = np.einsum("nij,nj->ni", rot, vc)
        v2 = np.einsum("ni,ni->n", vw, vw)
        rel = target[None, :] - pos
        with np.errstate(invalid="ignore", divide="ignore"):
            tau = np.einsum("ni,ni->n", rel, vw) / v2
        tau = np.where((v2 > 0) & (tau >= 0), tau, np.nan)
        return _shaped(tau, shape)


def _shaped(a: np.ndarray, shape) -> np.ndarray:
    return a.reshape(shape)[()]
