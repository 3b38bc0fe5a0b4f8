"""Pictures of optical flow: flow events over a time window, direction as hue (thesis Fig. 4.6).

Each pixel shows the mean flow vector of its flow events in the window, coloured by direction
on the HSV colour wheel (hue = angle: 0° = right, 90° = down, image coordinates; full
saturation and value); pixels without flow stay black. Sampled flow arrows (white, one per
``arrows_every_px`` grid cell with flow: the mean of its pixels' mean flow, see
:func:`evchain.report.overlay.draw_flow_arrows`) and a colour-wheel legend in the bottom-right
corner go on top.

* :func:`flow_image` draws from plain arrays (any run's data),
* :class:`FlowAccumulator` sums flow per pixel packet by packet (constant memory),
* :func:`save_png` writes a picture atomically,
* :func:`flow_image_from_file` renders a saved ``.npz`` (columns x, y, t, vx, vy and optional
  width, height, as written by the ``flow_image`` stage's ``save_npz``) or an HDF5 file with a
  ``flow`` or ``events`` group holding the same datasets.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from evchain.errors import DataError
from evchain.io.atomic import atomic_write_bytes


class FlowAccumulator:
    """Per-pixel sums of flow vectors for one time window ``[t0, t1)`` (None = unbounded)."""

    def __init__(self, width: int, height: int, t0: int | None = None, t1: int | None = None):
        self.width, self.height = int(width), int(height)
        self.t0, self.t1 = t0, t1
        self.sx = np.zeros((self.height, self.width), np.float64)
        self.sy = np.zeros((self.height, self.width), np.float64)
        self.n = np.zeros((self.height, self.width), np.int64)

    def add(self, x, y, t, vx, vy) -> None:
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        t = np.asarray(t, np.int64)
        keep = np.ones(len(t), bool)
        if self.t0 is not None:
            keep &= t >= self.t0
        if self.t1 is not None:
            keep &= t < self.t1
        keep &= (x >= 0) & (x < self.width) & (y >= 0) & (y < self.height)
        if not keep.any():
            return
        flat = y[keep] * self.width + x[keep]
        size = self.width * self.height
        self.sx.ravel()[:] += np.bincount(flat, np.asarray(vx, np.float64)[keep], size)
        self.sy.ravel()[:] += np.bincount(flat, np.asarray(vy, np.float64)[keep], size)
        self.n.ravel()[:] += np.bincount(flat, minlength=size)

    def image(self, scale: int = 1, wheel: bool = True, arrows_every_px: int = 16
              ) -> np.ndarray:
        return render(self.sx, self.sy, self.n, scale=scale, wheel=wheel,
                      arrows_every_px=arrows_every_px)


def render(sx: np.ndarray, sy: np.ndarray, n: np.ndarray, scale: int = 1,
           wheel: bool = True, arrows_every_px: int = 16) -> np.ndarray:
    """RGB uint8 ``[H*scale, W*scale, 3]`` from per-pixel flow sums and counts."""
    from evchain.report.overlay import draw_flow_arrows, paste_wheel
    from evchain.report.render import direction_colours

    h, w = n.shape
    img = np.zeros((h, w, 3), np.uint8)
    has = (n > 0) & ((sx != 0) | (sy != 0))
    if has.any():
        img[has] = direction_colours(sx[has], sy[has])
    if scale > 1:
        img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    if arrows_every_px and has.any():
        y, x = np.nonzero(has)
        img = draw_flow_arrows(img, x, y, sx[has] / n[has], sy[has] / n[has], scale,
                               arrows_every_px)
    if wheel:
        paste_wheel(img)
    return img


def flow_image(x, y, vx, vy, width: int, height: int, t=None,
               t_window_us: tuple[int, int] | None = None, scale: int = 1,
               wheel: bool = True, arrows_every_px: int = 16) -> np.ndarray:
    """The picture of flow events (arrays) inside ``t_window_us = (start, end)`` (all if None)."""
    t0, t1 = (None, None) if t_window_us is None else (int(t_window_us[0]), int(t_window_us[1]))
    if t is None:
        if t_window_us is not None:
            raise DataError("flow_image: a time window needs the event times t")
        t = np.zeros(len(np.asarray(x)), np.int64)
    acc = FlowAccumulator(width, height, t0, t1)
    acc.add(x, y, t, vx, vy)
    return acc.image(scale=scale, wheel=wheel, arrows_every_px=arrows_every_px)


def png_bytes(img: np.ndarray) -> bytes:
    import imageio.v3 as iio

    buf = io.BytesIO()
    iio.imwrite(buf, img, extension=".png")
    return buf.getvalue()


def save_png(path: str | Path, img: np.ndarray) -> Path:
    """Write ``img`` as PNG under ``path.partial`` and rename when complete."""
    path = Path(path)
    atomic_write_bytes(path, png_bytes(img))
    return path


def load_flow(path: str | Path) -> dict[str, np.ndarray]:
    """Columns x, y, t, vx, vy (and width, height when stored) of a saved flow file."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such flow file")
    cols = ("x", "y", "t", "vx", "vy")
    if path.suffix == ".npz":
        with np.load(path) as z:
            missing = [c for c in cols if c not in z.files]
            if missing:
                raise DataError(f"{path}: flow .npz lacks arrays {missing}; has {z.files}")
            out = {c: z[c] for c in cols}
            for c in ("width", "height"):
                if c in z.files:
                    out[c] = int(z[c])
        return out
    if path.suffix in (".h5", ".hdf5"):
        try:
            import h5py
        except ImportError:
            raise DataError(f"{path}: reading HDF5 needs h5py") from None
        with h5py.File(path, "r") as f:
            for group in ("flow", "events"):
                if group in f and all(c in f[group] for c in cols):
                    g = f[group]
                    out = {c: g[c][()] for c in cols}
                    for c in ("width", "height"):
                        if c in g.attrs:
                            out[c] = int(g.attrs[c])
                    return out
        raise DataError(f"{path}: no group 'flow' or 'events' with datasets {list(cols)}")
    raise DataError(f"{path}: unknown flow file type (expected .npz, .h5 or .hdf5)")


def flow_image_from_file(path: str | Path, out_png: str | Path,
                         t_window_us: tuple[int, int] | None = None, width: int | None = None,
                         height: int | None = None, scale: int = 2) -> Path:
    """Render a saved flow file (see :func:`load_flow`) to a PNG; the sensor size comes from the
    file or the arguments (else the events' extent)."""
    d = load_flow(path)
    w = width or d.get("width") or (int(np.max(d["x"])) + 1 if len(d["x"]) else 1)
    h = height or d.get("height") or (int(np.max(d["y"])) + 1 if len(d["y"]) else 1)
    img = flow_image(d["x"], d["y"], d["vx"], d["vy"], w, h, t=d["t"],
                     t_window_us=t_window_us, scale=scale)
    return save_png(out_png, img)
