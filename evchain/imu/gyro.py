"""Gyro samples as a function of time: bias and axis signs applied, interpolated, with gaps."""

from __future__ import annotations

from typing import Literal

import numpy as np

#: a gap between samples longer than this many median sample intervals (and at least
#: MIN_GAP_US) leaves the time in between without gyro data
GAP_FACTOR = 5.0
MIN_GAP_US = 5_000


class GyroTrack:
    """Gyro readings ``(t µs, gx, gy, gz deg/s)`` in the camera's axes, appended in time order;
    :meth:`rate` gives ``signs * (reading - bias)`` in rad/s at any time."""

    def __init__(self):
        self.clear()

    def clear(self) -> None:
        self.t = np.zeros(0, np.int64)
        self.g = np.zeros((0, 3), np.float64)

    def __len__(self) -> int:
        return len(self.t)

    def append(self, t: np.ndarray, g: np.ndarray) -> None:
        """Samples at times ``t`` (int64 µs, at or after the last one) with readings ``g``
        (``[n, 3]`` deg/s)."""
        if len(t):
            self.t = np.concatenate([self.t, np.asarray(t, np.int64)])
            self.g = np.concatenate([self.g, np.asarray(g, np.float64).reshape(-1, 3)])

    def until(self, t_us: float) -> GyroTrack:
        """A track of the samples before ``t_us`` (the rest left out)."""
        n = int(np.searchsorted(self.t, t_us, side="left"))
        out = GyroTrack()
        out.t, out.g = self.t[:n], self.g[:n]
        return out

    def trim(self, before_us: int) -> None:
        """Forget samples older than ``before_us`` (keeping the one before it)."""
        i = max(int(np.searchsorted(self.t, before_us, side="left")) - 1, 0)
        if i:
            self.t = self.t[i:]
            self.g = self.g[i:]

    def max_gap_us(self) -> float:
        if len(self.t) < 2:
            return float(MIN_GAP_US)
        return max(GAP_FACTOR * float(np.median(np.diff(self.t))), float(MIN_GAP_US))

    def rate(self, t_us, bias_dps, signs, interpolation: Literal["linear", "previous"] = "linear"
             ) -> tuple[np.ndarray, np.ndarray]:
        """``(w [..., 3] rad/s, covered [...] bool)`` at times ``t_us`` (µs, float allowed):
        linear between the samples around each time, or the latest sample at or before it
        (``previous``, jAER's choice). Times outside the samples, or inside a gap, are not
        covered (``w`` there is 0)."""
        t = np.asarray(t_us, np.float64)
        shape = t.shape
        t = t.ravel()
        w = np.zeros((len(t), 3))
        covered = np.zeros(len(t), bool)
        if len(self.t) == 0:
            return w.reshape(*shape, 3), covered.reshape(shape)
        ts = self.t.astype(np.float64)
        g = (self.g - np.asarray(bias_dps, np.float64)) * np.asarray(signs, np.float64)
        gap = self.max_gap_us()
        hi = np.searchsorted(ts, t, side="right")          # first sample after t
        lo = hi - 1                                          # last sample at or before t
        if interpolation == "previous":
            covered = (lo >= 0) & (t <= ts[-1] + gap)
            lo_c = np.clip(lo, 0, len(ts) - 1)
            covered &= (t - ts[lo_c]) <= gap
            w = np.where(covered[:, None], g[lo_c], 0.0)
        else:
            lo_c = np.clip(lo, 0, len(ts) - 1)
            hi_c = np.clip(hi, 0, len(ts) - 1)
            exact = (lo >= 0) & (ts[lo_c] == t)
            inside = (lo >= 0) & (hi < len(ts)) & ((ts[hi_c] - ts[lo_c]) <= gap)
            covered = exact | inside
            span = np.where(hi_c > lo_c, ts[hi_c] - ts[lo_c], 1.0)
            a = np.clip((t - ts[lo_c]) / span, 0.0, 1.0)[:, None]
            w = np.where(covered[:, None], g[lo_c] * (1.0 - a) + g[hi_c] * a, 0.0)
        return np.radians(w).reshape(*shape, 3), covered.reshape(shape)
