"""Source ``frames``: frame sequences rendered by any simulator, as FramePackets.

Inputs: a folder of images (sorted by file name), a video file (through imageio's plugins), or a
``.npz`` (arrays ``frames`` and optionally ``t``/``timestamps`` in µs) or ``.npy`` array of
shape [n, H, W] or [n, H, W, C]. Timestamps come from the ``.npz``, a ``timestamps_path`` (text,
one µs value per line, or ``.npy``) or ``fps``.

Conversion to linear intensity: integers are scaled to [0, 1] (uint8 by 255, uint16 by 65535),
floats are kept; ``encoding`` says whether the values are sRGB-gamma encoded (decoded with the
sRGB curve) or already linear; ``auto`` assumes sRGB for image and video files and linear for
arrays. RGB(A) becomes luminance with the Rec. 709 weights (0.2126, 0.7152, 0.0722) applied to
linear values; alpha is dropped.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FramePacket, Geometry
from evchain.errors import ConfigError, DataError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".gif",
                  ".exr", ".webp"}
REC709 = np.array([0.2126, 0.7152, 0.0722])


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (values in [0, 1])."""
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def to_luminance(img: np.ndarray, srgb: bool, where: str) -> np.ndarray:
    """One frame ([H, W] or [H, W, C]) of any supported dtype to float32 linear luminance."""
    a = np.asarray(img)
    if a.dtype == np.uint8:
        v = a.astype(np.float64) / 255.0
    elif a.dtype == np.uint16:
        v = a.astype(np.float64) / 65535.0
    elif a.dtype.kind == "f":
        v = a.astype(np.float64)
    elif a.dtype == bool:
        v = a.astype(np.float64)
    else:
        raise DataError(f"{where}: pixel type {a.dtype} not supported (uint8, uint16 or float)")
    if v.ndim == 3:
        c = v.shape[2]
        if c in (1, 2):          # grey (+ alpha)
            v = v[..., 0]
        elif c in (3, 4):
            v = v[..., :3]
        else:
            raise DataError(f"{where}: expected 1, 3 or 4 channels, got shape {a.shape}")
    elif v.ndim != 2:
        raise DataError(f"{where}: a frame must be [H, W] or [H, W, C], got shape {a.shape}")
    if not np.isfinite(v).all():
        bad = np.argwhere(~np.isfinite(v))[0]
        raise DataError(f"{where}: value not finite (NaN or inf) at (y={bad[0]}, x={bad[1]})")
    if (v < 0).any():
        bad = np.argwhere(v < 0)[0]
        raise DataError(f"{where}: negative value at (y={bad[0]}, x={bad[1]}); frames must be "
                        "intensities >= 0")
    if srgb:
        v = srgb_to_linear(v)
    if v.ndim == 3:
        v = v @ REC709
    return v.astype(np.float32)


class FramesSource(Filter):
    """Frames from an image folder, a video file or an .npz/.npy array, as linear luminance.

    Timestamps from the array file, a timestamps file or ``fps``; RGB to Rec. 709 luminance;
    8-bit, 16-bit and float input; sRGB-gamma or linear (``encoding``).
    """

    name = "frames"
    consumes = None
    produces = FramePacket
    input_paths = ("path", "timestamps_path")

    class Params(FilterParams):
        path: str = Field(..., description="image folder, video file, .npz or .npy")
        fps: float | None = Field(None, gt=0, description="frame rate when the input has no "
                                  "timestamps (t_k = t0_us + round(k * 1e6 / fps))")
        timestamps_path: str | None = Field(None, description="text (one µs value per line) "
                                            "or .npy file with one timestamp per frame")
        t0_us: int = Field(0, ge=0, description="time of the first frame when using fps")
        encoding: Literal["auto", "srgb", "linear"] = Field(
            "auto", description="auto: sRGB for image/video files, linear for arrays")
        frames_per_packet: int = Field(16, ge=1, description="frames per emitted packet")

    # -- opening ---------------------------------------------------------------------------
    def setup(self, params, context) -> None:
        self.params = params
        path = Path(params.path)
        if not path.is_absolute() and not path.exists():
            path = Path.cwd() / path
        if not path.exists():
            raise ConfigError(f"frames: {params.path!r} does not exist", key="path")
        self._path = path
        if path.is_dir():
            self._kind = "folder"
            self._files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self._files:
                raise DataError(f"{path}: no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
            self._count = len(self._files)
        elif path.suffix.lower() in (".npz", ".npy"):
            self._kind = "array"
            self._array, ts = self._load_array(path)
            self._count = len(self._array)
            if ts is not None and params.timestamps_path is None:
                self._times = self._check_times(np.asarray(ts), str(path))
        else:
            self._kind = "video"
            self._count = None
        srgb = params.encoding == "srgb" or (params.encoding == "auto" and self._kind != "array")
        self._srgb = srgb
        first = self._first_frame()
        h, w = first.shape
        context.geometry = Geometry(w, h)
        if not hasattr(self, "_times"):
            self._times = self._timestamps()
        super().setup(params, context)

    def _load_array(self, path: Path):
        try:
            data = np.load(path, allow_pickle=False)
        except Exception as exc:
            raise DataError(f"{path}: cannot read as numpy array file ({exc})") from exc
        if isinstance(data, np.lib.npyio.NpzFile):
            with data:
                if "frames" not in data.files:
                    raise DataError(f"{path}: .npz must hold an array 'frames' (has "
                                    f"{data.files})")
                frames = data["frames"]
                ts = next((data[k] for k in ("t", "timestamps", "t_us") if k in data.files), None)
        else:
            frames, ts = data, None
        if frames.ndim not in (3, 4):
            raise DataError(f"{path}: frames must be [n, H, W] or [n, H, W, C], got shape "
                            f"{frames.shape}")
        return frames, ts

    def _first_frame(self) -> np.ndarray:
        if self._kind == "array":
            return to_luminance(self._array[0], self._srgb, f"{self._path} frame 0")
        if self._kind == "folder":
            return self._read_image(0)
        for frame in self._iter_video():
            return frame
        raise DataError(f"{self._path}: the video has no frames")

    def _read_image(self, i: int) -> np.ndarray:
        import imageio.v3 as iio

        f = self._files[i]
        try:
            img = iio.imread(f)
        except Exception as exc:
            raise DataError(f"{f}: cannot read image ({exc})") from exc
        return to_luminance(img, self._srgb, str(f))

    def _iter_video(self) -> Iterator[np.ndarray]:
        import imageio.v3 as iio

        try:
            it = iio.imiter(self._path)
            for i, img in enumerate(it):
                yield to_luminance(img, self._srgb, f"{self._path} frame {i}")
        except DataError:
            raise
        except Exception as exc:
            msg = str(exc)
            if "plugin" in msg.lower() or "backend" in msg.lower() or "find" in msg.lower():
                raise DataError(f"{self._path}: no video backend can read this file; install "
                                "one with `pip install imageio[pyav]` (or imageio[ffmpeg]); "
                                f"imageio said: {msg}") from exc
            raise DataError(f"{self._path}: cannot read video ({msg})") from exc

    def _timestamps(self) -> np.ndarray | None:
        p = self.params
        if p.timestamps_path is not None:
            tp = Path(p.timestamps_path)
            try:
                ts = np.load(tp) if tp.suffix == ".npy" else np.loadtxt(tp, ndmin=1)
            except Exception as exc:
                raise DataError(f"{tp}: cannot read timestamps ({exc})") from exc
            return self._check_times(np.asarray(ts), str(tp))
        if p.fps is None and self._kind == "video":
            try:
                import imageio.v3 as iio

                fps = iio.immeta(self._path).get("fps")
            except Exception:
                fps = None
            if fps:
                self._video_fps = float(fps)
                return None
        if p.fps is None:
            raise ConfigError(f"frames: {self._path} has no timestamps; give fps or "
                              "timestamps_path", key="fps")
        return None if self._count is None else self._fps_times(p.fps)

    def _fps_times(self, fps: float, n: int | None = None) -> np.ndarray:
        n = self._count if n is None else n
        return self.params.t0_us + np.round(np.arange(n) * 1e6 / fps).astype(np.int64)

    def _check_times(self, ts: np.ndarray, where: str) -> np.ndarray:
        if ts.ndim != 1:
            raise DataError(f"{where}: timestamps must be 1-D, got shape {ts.shape}")
        if not np.isfinite(ts).all():
            raise DataError(f"{where}: timestamp {int(np.argmax(~np.isfinite(ts)))} not finite")
        if self._count is not None and len(ts) != self._count:
            raise DataError(f"{where}: {len(ts)} timestamps for {self._count} frames")
        ts = np.asarray(ts).astype(np.int64)
        d = np.diff(ts)
        if np.any(d <= 0):
            i = int(np.argmax(d <= 0)) + 1
            raise DataError(f"{where}: timestamps must increase; frame {i} at {ts[i]} us "
                            f"follows {ts[i - 1]} us")
        return ts

    def time_span_us(self) -> tuple[int, int] | None:
        if self._times is None or not len(self._times):
            return None
        return int(self._times[0]), int(self._times[-1]) + 1

    # -- streaming -------------------------------------------------------------------------
    def _frames(self) -> Iterator[np.ndarray]:
        if self._kind == "array":
            for i in range(len(self._array)):
                yield to_luminance(self._array[i], self._srgb, f"{self._path} frame {i}")
        elif self._kind == "folder":
            for i in range(len(self._files)):
                yield self._read_image(i)
        else:
            yield from self._iter_video()

    def packets(self) -> Iterator[FramePacket]:
        g = self.context.geometry
        fpp = self.params.frames_per_packet
        fps = self.params.fps or getattr(self, "_video_fps", None)
        buf: list[np.ndarray] = []
        start = 0
        for i, frame in enumerate(self._frames()):
            if frame.shape != g.shape:
                raise DataError(f"{self._where(i)}: frame shape {frame.shape} differs from the "
                                f"first frame's {g.shape}")
            buf.append(frame)
            if len(buf) == fpp:
                yield self._packet(buf, start, fps, last=False)
                start += len(buf)
                buf = []
        if buf:
            yield self._packet(buf, start, fps, last=True)

    def _where(self, i: int) -> str:
        return str(self._files[i]) if self._kind == "folder" else f"{self._path} frame {i}"

    def _time(self, i: int, fps) -> int:
        if self._times is not None:
            if i >= len(self._times):
                raise DataError(f"{self._where(i)}: more frames than timestamps")
            return int(self._times[i])
        if not fps:
            raise ConfigError("frames: the video has no frame rate; give fps", key="fps")
        return self.params.t0_us + int(round(i * 1e6 / fps))

    def _packet(self, buf, start, fps, last: bool) -> FramePacket:
        n = len(buf)
        t = np.array([self._time(start + k, fps) for k in range(n)], np.int64)
        t_end = t[-1] + 1
        if not last:
            try:
                t_end = self._time(start + n, fps)
            except DataError:
                t_end = t[-1] + 1
        return FramePacket(geometry=self.context.geometry, t_start=int(t[0]), t_end=int(t_end),
                           frames=np.stack(buf), t=t)
