"""Lengths and speeds in pixels that follow the camera.

A length in px chosen on the reference camera (320x240, 35 deg vertical field of view, focal
length ``REFERENCE_FOCAL_PX`` = 380.6 px) stands for an angle, and a speed in px/s for an
angular speed: on a camera with focal length f the same angle spans ``f / REFERENCE_FOCAL_PX``
times as many pixels (a 640x480 sensor with the same field of view: twice as many). Filters
whose px and px/s parameters default to None derive them with :func:`px_scale` from their
values on the reference camera (:func:`derived`). A time that stands for a distance on the
pixel grid travelled at an image speed (a flow's window: the time in which an edge crosses so
many pixels) shrinks by the same factor, since the speeds in px/s grow with it
(:func:`derived_us`). Lengths on the pixel grid itself (a neighbourhood's half-width, a
distance an edge must cross to be resolved) are not derived.
"""

from __future__ import annotations

import math

from evchain.core.packets import Geometry
from evchain.errors import ConfigError

#: the reference camera's focal length, px: 240 rows, 35 deg vertical field of view
REFERENCE_FOCAL_PX = 120.0 / math.tan(math.radians(35.0) / 2.0)


def px_scale(geometry: Geometry) -> float:
    """``f / REFERENCE_FOCAL_PX``: how many px of this camera an angle spanning one px of the
    reference camera spans. Without a focal length the reference camera's field of view is
    assumed (the scale is the height over 240)."""
    if geometry.f is None:
        return geometry.height / 240.0
    return float(geometry.f) / REFERENCE_FOCAL_PX


def derived(value: float | None, reference_px: float, geometry: Geometry) -> float:
    """``value`` when given, else ``reference_px`` (its value on the reference camera) scaled
    by :func:`px_scale`."""
    return float(value) if value is not None else reference_px * px_scale(geometry)


def derived_us(value: int | None, reference_us: int, geometry: Geometry) -> int:
    """``value`` when given, else ``reference_us`` (its value on the reference camera) divided
    by :func:`px_scale`, rounded to whole µs: the time in which an image speed, which grows
    with the scale, covers the same pixels."""
    return int(value) if value is not None else round(reference_us / px_scale(geometry))


def check_window_order(stage: str, window: int, longest: int, shortest: int,
                       geometry: Geometry) -> None:
    """A flow's windows on this camera (after deriving): the longest (adaptive) window, when on,
    must exceed ``window`` and the shortest, when on, be shorter; else a ConfigError naming
    ``stage`` and the camera."""
    size = f"on this {geometry.width}x{geometry.height} camera"
    if longest and longest <= window:
        raise ConfigError(f"{stage}: max_window_us ({longest}) must exceed window_us "
                          f"({window}) {size}, or be 0 (off)")
    if shortest and shortest >= window:
        raise ConfigError(f"{stage}: min_window_us ({shortest}) must be shorter than "
                          f"window_us ({window}) {size}, or be 0 (off)")
