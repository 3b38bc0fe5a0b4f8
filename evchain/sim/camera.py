"""Pinhole camera of the simulator: resolution, vertical field of view, supersampling.

Conventions (``docs/explanation/scene.md``): image x right, y down, origin at the top-left
pixel's centre, principal point at the image centre ((W-1)/2, (H-1)/2); camera X right, Y down,
Z forward; f = (H/2) / tan(FOV/2) in pixels (thesis eq. 7.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from evchain.core.packets import Geometry
from evchain.errors import ConfigError


def focal_from_fov(height: int, fov_deg: float) -> float:
    """Focal length in pixels from the image height and the vertical field of view."""
    if not 0 < fov_deg < 180:
        raise ConfigError(f"fov_deg must lie in (0, 180) degrees, got {fov_deg}")
    if height < 1:
        raise ConfigError(f"image height must be at least 1 pixel, got {height}")
    return (height / 2.0) / math.tan(math.radians(fov_deg) / 2.0)


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fov_deg: float
    supersample: int = 1

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ConfigError(f"resolution must be at least 1x1, got {self.width}x{self.height}")
        if self.supersample < 1:
            raise ConfigError(f"supersample must be >= 1, got {self.supersample}")
        focal_from_fov(self.height, self.fov_deg)

    @property
    def f(self) -> float:
        return focal_from_fov(self.height, self.fov_deg)

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2.0

    @property
    def geometry(self) -> Geometry:
        return Geometry(width=self.width, height=self.height, f=self.f, cx=self.cx, cy=self.cy)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates [n, 2] of camera-frame points [n, 3] (pinhole, no distortion)."""
        p = np.asarray(points_cam, float)
        return np.stack([self.f * p[:, 0] / p[:, 2] + self.cx,
                         self.f * p[:, 1] / p[:, 2] + self.cy], axis=1)
