"""The world model: ground plane with a road, axis-aligned boxes with materials, sun and sky.

Everything the kernels need is a few numpy arrays (layouts in
:mod:`evchain.kernels.scene_geometry`). :mod:`evchain.sim.scenarios` fills them for each scenario.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MAT_PLAIN, MAT_WINDOWS, MAT_ORANGE, MAT_ORANGE_LINES, MAT_CAR = 0, 1, 2, 3, 4
# Object ids of what a ray sees (truth_query in evchain.kernels.scene_truth): a box's index in
# World.boxes (>= 0), or one of these.
OBJECT_SKY = -1
OBJECT_GROUND = -2
# Label of the boxes that make up the obstacle (the car across the ego lane).
OBSTACLE_LABEL = "car"


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

    @property
    def obstacle_ids(self) -> np.ndarray:
        """Indices (int64) of the boxes labelled ``OBSTACLE_LABEL``; empty without an obstacle."""
        return np.array([i for i, lb in enumerate(self.labels) if lb == OBSTACLE_LABEL], np.int64)

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


# ----------------------------------------------------------------------------- ground textures

#: side of every ground texture (texels, a power of two; the textures repeat with this period)
TEX_N = 512
#: mip levels per texture: TEX_N, TEX_N / 2, ..., 1 texels
TEX_LEVELS = 10
#: ground noise textures: (texel size m, ((cell size in texels, amplitude, seed offset), ...))
#: 0 asphalt (2 m, 0.5 m, 0.125 m cells), 1 grass (4 m, 1 m, 0.25 m), 2 paving (4 m, 0.5 m)
GROUND_TEXTURES = (
    (1.0 / 16.0, ((32, 0.08, 0), (8, 0.06, 1), (2, 0.05, 2))),
    (1.0 / 8.0, ((32, 0.05, 4), (8, 0.04, 5), (2, 0.03, 6))),
    (1.0 / 8.0, ((32, 0.06, 7), (4, 0.04, 8))),
)


def hash3_np(i, j, s) -> np.ndarray:
    """numpy twin of :func:`evchain.kernels.scene_shading.hash3` (integers to [0, 1))."""
    i, j, s = (np.asarray(v, np.int64) for v in (i, j, s))
    h = ((i * 374761393) ^ (j * 668265263) ^ (s * 1442695041)) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / 16777216.0


def ground_textures(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pre-filtered (mip-mapped) ground noise textures.

    Level 0 of texture k holds, at texel (i, j) (world x = i * texel, y = j * texel, repeating
    every TEX_N texels), the sum of zero-mean value-noise octaves amplitude * (hash(cell) - 0.5)
    with square cells of the given size; level l + 1 is the 2x2 mean of level l. Returns
    (texels float32, flat: texture k level l row j column i at offsets[k, l] + j * n_l + i with
    n_l = TEX_N >> l; inverse texel sizes [3] of level 0 in 1/m; offsets [3, TEX_LEVELS] int64).
    """
    levels, offsets, inv = [], np.zeros((len(GROUND_TEXTURES), TEX_LEVELS), np.int64), []
    pos = 0
    jj, ii = np.mgrid[0:TEX_N, 0:TEX_N]
    for k, (texel, octaves) in enumerate(GROUND_TEXTURES):
        img = np.zeros((TEX_N, TEX_N))
        for cell, amp, off in octaves:
            img += amp * (hash3_np(ii // cell, jj // cell, seed + off) - 0.5)
        inv.append(1.0 / texel)
        for lv in range(TEX_LEVELS):
            offsets[k, lv] = pos
            levels.append(img.astype(np.float32).ravel())
            pos += img.size
            n = img.shape[0] // 2
            if n:
                img = img.reshape(n, 2, n, 2).mean(axis=(1, 3))
    return np.concatenate(levels), np.array(inv), offsets
