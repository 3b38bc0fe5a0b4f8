"""The world model: ground plane with a road, axis-aligned boxes with materials, sun and sky.

Everything the kernels need is a few numpy arrays (layouts in :mod:`evchain.kernels.scene`).
:mod:`evchain.sim.scenarios` fills them for each scenario.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MAT_PLAIN, MAT_WINDOWS, MAT_ORANGE, MAT_ORANGE_LINES, MAT_CAR = 0, 1, 2, 3, 4


@dataclass
class World:
    segs: np.ndarray                       # driving line segments [M, 8]
    ground: np.ndarray                     # ground/road parameters [9]
    light: np.ndarray                      # sun direction (3), sun, ambient, sky horizon, zenith
    route_m: float                         # length of the route (driving line) in m
    obstacle_rear: np.ndarray | None = None  # world point of the obstacle's rear face centre
    boxes: list[tuple[float, ...]] = field(default_factory=list)
    mats: list[int] = field(default_factory=list)
    pars: list[tuple[float, float, float, float]] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)

    def add_box(self, lo, hi, mat: int = MAT_PLAIN, par=(0.3, 0.0, 0.0, 0.0), label: str = ""):
        lo = [float(v) for v in lo]
        hi = [float(v) for v in hi]
        if any(h <= lo_ for lo_, h in zip(lo, hi, strict=True)):
            raise ValueError(f"empty box {lo} .. {hi}")
        self.boxes.append((*lo, *hi))
        self.mats.append(int(mat))
        self.pars.append(tuple(float(p) for p in (list(par) + [0.0] * 4)[:4]))
        self.labels.append(label)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(boxes [N, 6], materials [N] int64, parameters [N, 4]); N may be 0."""
        return (np.array(self.boxes, np.float64).reshape(-1, 6),
                np.array(self.mats, np.int64),
                np.array(self.pars, np.float64).reshape(-1, 4))


def make_ground(centre_offset: float, half_width: float, edge_line: float, sidewalk: float,
                beyond: int, seed: int, line_width: float = 0.15, dash: float = 3.0,
                period: float = 9.0) -> np.ndarray:
    return np.array([centre_offset, half_width, line_width, edge_line, sidewalk, dash, period,
                     float(beyond), float(seed % 100003)], np.float64)


def make_light(azimuth_deg: float, elevation_deg: float, sun: float = 0.9, ambient: float = 0.45,
               sky_horizon: float = 1.6, sky_zenith: float = 1.0) -> np.ndarray:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el),
                     sun, ambient, sky_horizon, sky_zenith], np.float64)
