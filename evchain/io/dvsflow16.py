"""Ground truth of the DVSFLOW16 synthetic samples (Rueckauer & Delbruck 2016) from ``.mat`` files.

A file (MATLAB v5, read with ``scipy.io.loadmat``) holds ``vxGT``, ``vyGT`` (per-pixel flow in
px/s, arrays ``[rows, cols]`` = ``[180, 240]`` for the DAVIS240) and ``ts`` = ``[t0, t1]`` (µs),
the time window in which the field is valid. Layout as jAER uses it: the column is jAER's x
(already flipped, the same as evchain's x), the row is jAER's y with its origin at the
bottom-left and y up. In evchain's top-left coordinates: row = H-1-y, and vy changes sign.

Entries where both components are exactly 0 mean "no ground truth here" (the translating
square's file is zero everywhere off the square's edges) and give NaN, as do times outside the
half-open window ``[t0, t1)`` and positions outside the array.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evchain.errors import DataError


class DVSFLOW16Truth:
    """Flow ground truth from a DVSFLOW16 ``gt*.mat`` file: ``flow(x, y, t_us) -> (vx, vy)``.

    ``y_up=False`` (default) expects evchain's top-left pixel coordinates (as the ``aedat``
    reader delivers them); ``y_up=True`` takes jAER's bottom-left coordinates as they are.
    ``height``/``width``, if given, must match the arrays (a sensor-size mismatch is an error).
    """

    def __init__(self, path: str | Path, height: int | None = None, width: int | None = None,
                 y_up: bool = False):
        self.path = Path(path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: DVSFLOW16 ground-truth file not found")
        try:
            from scipy.io import loadmat

            mat = loadmat(str(self.path))
        except Exception as exc:  # scipy raises ValueError, MatReadError, OSError ...
            raise DataError(f"{self.path}: not a readable MATLAB .mat file "
                            f"({type(exc).__name__}: {exc})") from None
        missing = [k for k in ("vxGT", "vyGT", "ts") if k not in mat]
        if missing:
            raise DataError(f"{self.path}: expected variables vxGT, vyGT, ts in the .mat file; "
                            f"missing {missing} (has {sorted(k for k in mat if k[0] != '_')})")
        vx = np.asarray(mat["vxGT"], np.float64)
        vy = np.asarray(mat["vyGT"], np.float64)
        ts = np.asarray(mat["ts"], np.float64).ravel()
        if vx.ndim != 2 or vx.shape != vy.shape:
            raise DataError(f"{self.path}: vxGT and vyGT must be 2-D arrays of one shape, got "
                            f"{vx.shape} and {vy.shape}")
        if ts.size != 2 or not np.all(np.isfinite(ts)) or ts[1] < ts[0]:
            raise DataError(f"{self.path}: ts must be [t_start, t_end] in us, got {ts.tolist()}")
        if (height is not None and height != vx.shape[0]) or (width is not None
                                                              and width != vx.shape[1]):
            raise DataError(f"{self.path}: ground truth is {vx.shape[1]}x{vx.shape[0]} px but "
                            f"the sensor is {width}x{height} px")
        if not (np.all(np.isfinite(vx)) and np.all(np.isfinite(vy))):
            raise DataError(f"{self.path}: vxGT/vyGT contain non-finite values")
        none = (vx == 0) & (vy == 0)
        if not y_up:
            vx, vy, none = vx[::-1], -vy[::-1], none[::-1]
        self.vx = np.where(none, np.nan, vx)
        self.vy = np.where(none, np.nan, vy)
        self.t_start_us = float(ts[0])
        self.t_end_us = float(ts[1])
        self.height, self.width = vx.shape

    def flow(self, x, y, t_us):
        """(vx, vy) px/s at pixels (x, y) and times t_us; NaN where unknown."""
        x = np.asarray(x)
        y = np.asarray(y)
        t = np.asarray(t_us, np.float64)
        shape = np.broadcast_shapes(x.shape, y.shape, t.shape)
        xi = np.broadcast_to(np.rint(x).astype(np.int64), shape)
        yi = np.broadcast_to(np.rint(y).astype(np.int64), shape)
        t = np.broadcast_to(t, shape)
        ok = ((xi >= 0) & (xi < self.width) & (yi >= 0) & (yi < self.height)
              & (t >= self.t_start_us) & (t < self.t_end_us))
        xc = np.where(ok, xi, 0)
        yc = np.where(ok, yi, 0)
        vx = np.where(ok, self.vx[yc, xc], np.nan)
        vy = np.where(ok, self.vy[yc, xc], np.nan)
        if vx.ndim == 0:
            return float(vx), float(vy)
        return vx, vy
