"""Pictures of events and flow as RGB arrays (uint8 [H, W, 3]), shared by plots and videos.

Events: ON white, OFF blue-grey on black. Flow: direction as hue on the colour wheel (0° = right,
90° = down, as in image coordinates), full brightness. Markers: the estimated FOE in yellow, the
true one in red (as in the thesis's figures).
"""

from __future__ import annotations

import numpy as np

YELLOW = (255, 220, 0)
RED = (230, 30, 30)


def direction_colours(vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
    """RGB uint8 [n, 3] for flow directions (hue = angle, full saturation and value)."""
    import matplotlib.colors

    hue = (np.arctan2(vy, vx) / (2 * np.pi)) % 1.0
    hsv = np.stack([hue, np.ones_like(hue), np.ones_like(hue)], axis=-1)
    return (matplotlib.colors.hsv_to_rgb(hsv) * 255).astype(np.uint8)


def event_image(height: int, width: int, x: np.ndarray, y: np.ndarray, p: np.ndarray,
                vx: np.ndarray | None = None, vy: np.ndarray | None = None) -> np.ndarray:
    """Events drawn on black; later events overwrite earlier ones at the same pixel."""
    img = np.zeros((height, width, 3), np.uint8)
    if vx is not None:
        img[y, x] = direction_colours(vx, vy)
    else:
        img[y, x] = np.where((p > 0)[:, None], np.uint8(255), np.array([70, 90, 200], np.uint8))
    return img


def draw_cross(img: np.ndarray, x: float, y: float, colour, size: int = 5) -> None:
    """A plus sign centred at (x, y), clipped to the image (NaN positions are skipped)."""
    if not (np.isfinite(x) and np.isfinite(y)):
        return
    h, w = img.shape[:2]
    xi, yi = int(round(x)), int(round(y))
    for d in range(-size, size + 1):
        for u, v in ((xi + d, yi), (xi, yi + d)):
            if 0 <= u < w and 0 <= v < h:
                img[v, u] = colour


def colour_wheel(size: int = 41) -> np.ndarray:
    """A legend: the colour of every flow direction around a disc."""
    c = (size - 1) / 2
    yy, xx = np.mgrid[0:size, 0:size] - c
    img = np.zeros((size, size, 3), np.uint8)
    inside = np.hypot(xx, yy) <= c
    img[inside] = direction_colours(xx[inside], yy[inside])
    return img
