"""The gyro's motion field and rate as ground truth (:class:`~evchain.core.truth.FlowTruth`,
:class:`~evchain.core.truth.RotationTruth`)."""

from __future__ import annotations

import numpy as np

from evchain.imu.calibrate import Camera
from evchain.imu.gyro import GyroTrack
from evchain.imu.rotflow import rotational_flow


class ImuFlowTruth:
    """``flow(x, y, t_us)``: the flow a purely rotating camera sees, from its gyro;
    ``angular_velocity(t_us)``: the gyro's rate itself.

    The rate at event time ``t`` is the gyro's at ``t + camera.offset_us`` (bias removed, axis
    signs applied, interpolated); the flow follows from it, the focal length and the principal
    point (:mod:`evchain.imu.rotflow`). NaN where it is no truth: before a camera is set, where
    the gyro has no samples, in time bins that are not marked valid (:meth:`set_bin`: the
    events there disagree with a pure rotation, or were not checked), and where the flow is
    slower than ``min_speed_pxs`` (there the gyro's noise and bias are a large part of it).

    The angular velocity is the truth wherever the gyro has samples, translation or not (a
    gyro measures rotation alone): NaN only before a camera is set and where the gyro has no
    samples. The gyro says nothing about translation: ``foe`` and ``ttc`` are NaN throughout
    (where the bins pass the rotation check the camera does not translate, so it has no
    heading and approaches nothing; elsewhere they are unknown), so that FOE scorers run on a
    recording and score the rotation rate alone.
    """

    def __init__(self, bin_us: int = 100_000, min_speed_pxs: float = 0.0):
        self.bin_us = int(bin_us)
        self.min_speed_pxs = float(min_speed_pxs)
        self.gyro = GyroTrack()
        self.clear()

    def clear(self) -> None:
        self.gyro.clear()
        self.camera: Camera | None = None
        self._bins = np.zeros(0, np.int64)
        self._ok = np.zeros(0, bool)

    def set_bin(self, k: int, valid: bool) -> None:
        """Mark time bin ``[k bin_us, (k+1) bin_us)`` valid or not (bins in increasing order)."""
        self._bins = np.append(self._bins, np.int64(k))
        self._ok = np.append(self._ok, bool(valid))

    def bin_valid(self, t_us) -> np.ndarray:
        """Whether the bins of times ``t_us`` are marked valid (unmarked bins are not)."""
        k = np.floor_divide(np.asarray(t_us, np.float64), self.bin_us).astype(np.int64)
        if len(self._bins) == 0:
            return np.zeros(k.shape, bool)
        i = np.clip(np.searchsorted(self._bins, k), 0, len(self._bins) - 1)
        return (self._bins[i] == k) & self._ok[i]

    def rotation_flow(self, x, y, t_us) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(u, v, covered)``: the gyro's flow wherever the gyro has samples, bins and speed
        not considered (``u, v`` are 0 where not covered)."""
        x, y, t = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                      np.asarray(t_us, np.float64))
        cam = self.camera
        if cam is None:
            z = np.zeros(x.shape)
            return z, z.copy(), np.zeros(x.shape, bool)
        w, covered = self.gyro.rate(t + cam.offset_us, cam.bias_dps, cam.signs,
                                    cam.interpolation)
        u, v = rotational_flow(x, y, w, cam.f, cam.cx, cam.cy)
        return u, v, covered

    def angular_velocity(self, t_us) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(wx, wy, wz)`` rad/s about the camera's axes at ``t_us``: the gyro's at
        ``t_us + offset_us``, bias removed, axis signs applied; NaN where the gyro has no
        samples or no camera is set (:class:`~evchain.core.truth.RotationTruth`)."""
        t = np.asarray(t_us, np.float64)
        cam = self.camera
        if cam is None:
            nan = np.full(t.shape, np.nan)[()]
            return nan, nan, nan
        w, covered = self.gyro.rate(t + cam.offset_us, cam.bias_dps, cam.signs,
                                    cam.interpolation)
        w = np.where(covered[..., None], w, np.nan)
        return w[..., 0][()], w[..., 1][()], w[..., 2][()]

    def foe(self, t_us) -> tuple[np.ndarray, np.ndarray]:
        """NaN: the gyro tells no heading (see the class docstring)."""
        nan = np.full(np.shape(t_us), np.nan)[()]
        return nan, nan

    def ttc(self, t_us) -> np.ndarray:
        """NaN: the gyro tells no approach (see the class docstring)."""
        return np.full(np.shape(t_us), np.nan)[()]

    def valid(self, x, y, t_us) -> np.ndarray:
        """Where :meth:`flow` is finite."""
        u, v, covered = self.rotation_flow(x, y, t_us)
        return covered & self.bin_valid(np.broadcast_to(np.asarray(t_us, np.float64),
                                                        u.shape)) \
            & (np.hypot(u, v) >= self.min_speed_pxs)

    def flow(self, x, y, t_us):
        """(vx, vy) px/s at pixels ``(x, y)`` and times ``t_us``; NaN where it is no truth."""
        u, v, covered = self.rotation_flow(x, y, t_us)
        ok = covered & self.bin_valid(np.broadcast_to(np.asarray(t_us, np.float64), u.shape)) \
            & (np.hypot(u, v) >= self.min_speed_pxs)
        u = np.where(ok, u, np.nan)
        v = np.where(ok, v, np.nan)
        if u.ndim == 0:
            return float(u), float(v)
        return u, v
