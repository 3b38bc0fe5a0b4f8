"""Pictures of a simulated drive: the frame (tone-mapped), its depth and its ground-truth flow.

Flow is drawn with direction as hue and magnitude as brightness (saturating at the 99th
percentile, printed into the file name). Used by the ``scene_preview`` sink and usable directly:

>>> from evchain.sim.preview import write_preview
>>> write_preview(renderer.render(1e6), 1.0, "preview", "high-rise", truth)   # doctest: +SKIP
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from evchain.core.truth import DepthTruth, FlowTruth, Truth
from evchain.io.atomic import atomic_write_bytes

WHITE = 1.6   # linear intensity shown as white (the sky at the horizon)


def tone_map(frame: np.ndarray, white: float = WHITE) -> np.ndarray:
    """Linear intensity to 8-bit grey with a 2.2 gamma."""
    return (np.clip(frame / white, 0.0, 1.0) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


def depth_image(depth: np.ndarray, z_min: float = 1.0, z_max: float = 500.0) -> np.ndarray:
    """Near = bright, far = dark (log scale), sky (inf) black."""
    z = np.clip(depth, z_min, z_max)
    v = 1.0 - np.log(z / z_min) / np.log(z_max / z_min)
    v = np.where(np.isfinite(depth), v, 0.0)
    return (v * 255 + 0.5).astype(np.uint8)


def flow_image(vx: np.ndarray, vy: np.ndarray, scale: float | None = None
               ) -> tuple[np.ndarray, float]:
    """RGB image: hue = direction of (vx, vy), value = |v| / scale (99th percentile if None)."""
    from matplotlib.colors import hsv_to_rgb

    mag = np.hypot(vx, vy)
    if scale is None:
        finite = mag[np.isfinite(mag)]
        scale = float(np.percentile(finite, 99)) if finite.size else 1.0
    scale = max(scale, 1e-9)
    hue = (np.arctan2(vy, vx) / (2 * np.pi)) % 1.0
    val = np.clip(np.nan_to_num(mag / scale), 0.0, 1.0)
    rgb = hsv_to_rgb(np.stack([hue, np.ones_like(hue), val], axis=-1))
    return (rgb * 255 + 0.5).astype(np.uint8), scale


def png_bytes(image: np.ndarray) -> bytes:
    import imageio.v3 as iio

    buf = io.BytesIO()
    iio.imwrite(buf, image, extension=".png")
    return buf.getvalue()


def write_preview(frame: np.ndarray, t_s: float, out_dir: str | Path, prefix: str,
                  truth: Truth | None = None) -> list[Path]:
    """Write ``{prefix}_t{ms}ms_frame.png`` of ``frame`` (float32 [H, W], linear intensity, the
    frame at ``t_s``) and, when ``truth`` has depth and flow (``DepthTruth`` and ``FlowTruth``),
    ``_depth.png`` and ``_flow.png`` at ``t_s``; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_us = t_s * 1e6
    stem = f"{prefix}_t{int(round(t_s * 1000)):06d}ms"
    written = []
    path = out / f"{stem}_frame.png"
    atomic_write_bytes(path, png_bytes(tone_map(frame)))
    written.append(path)
    if isinstance(truth, DepthTruth) and isinstance(truth, FlowTruth):
        h, w = frame.shape
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
        if hasattr(truth, "depth_and_flow"):     # one query instead of two (SceneTruth)
            depth, vx, vy = truth.depth_and_flow(xs, ys, t_us)
        else:
            depth = truth.depth(xs, ys, t_us)
            vx, vy = truth.flow(xs, ys, t_us)
        path = out / f"{stem}_depth.png"
        atomic_write_bytes(path, png_bytes(depth_image(np.asarray(depth))))
        written.append(path)
        img, scale = flow_image(np.asarray(vx), np.asarray(vy))
        path = out / f"{stem}_flow.png"
        atomic_write_bytes(path, png_bytes(img))
        written.append(path)
    return written
