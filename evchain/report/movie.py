"""Movie files frame by frame: animated GIF (imageio with pillow) or MP4 (H.264 through
imageio-ffmpeg, ``pip install 'evchain[video]'``), written to a path the caller chooses (the
``.partial`` name of an :class:`~evchain.io.atomic.AtomicFile`), so the container is given
explicitly instead of guessed from the file name.

Timing: a GIF stores each frame's delay in whole hundredths of a second, and viewers show
delays below 20 ms as 100 ms, so a GIF plays at ``100 / round(100 / fps)`` frames per second
(25 fps: 40 ms, exact; 30 fps: 30 ms, 33.3 fps) and at most 50. An MP4 plays at ``fps``
exactly. H.264 in yuv420p needs an even width and height: odd frames are padded with one black
row or column.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evchain.errors import ConfigError

GIF_MIN_DELAY_CS = 2  # hundredths of a second; shorter delays are shown as 10 by viewers


def gif_delay_ms(fps: float) -> int:
    """The frame delay a GIF can store for ``fps``: whole hundredths of a second, >= 20 ms."""
    cs = round(100.0 / fps)
    if cs < GIF_MIN_DELAY_CS:
        raise ConfigError(f"a GIF plays at most 50 frames per second (frame delays of whole "
                          f"hundredths of a second, at least 0.02 s), got fps {fps:g}; use "
                          ".mp4 for faster playback", key="video.fps")
    return 10 * cs


class MovieWriter:
    """``append(frame)`` RGB uint8 ``[H, W, 3]`` frames of one size, then ``close()``."""

    def __init__(self, path: str | Path, kind: str, fps: float):
        self.path, self.kind, self.fps = Path(path), kind, float(fps)
        self._gif = self._mp4 = None
        if kind == "gif":
            import imageio.v2 as iio

            # imageio's pillow writer takes the delay in milliseconds
            self._gif = iio.get_writer(self.path, format="GIF", mode="I",
                                       duration=gif_delay_ms(fps), loop=0)
        elif kind != "mp4":
            raise ConfigError(f"unknown movie kind {kind!r}; expected gif or mp4")
        else:
            try:
                import imageio_ffmpeg  # noqa: F401
            except ImportError:
                raise ConfigError("writing .mp4 needs: pip install 'evchain[video]'",
                                  key="video.path") from None

    def append(self, frame: np.ndarray) -> None:
        if self._gif is not None:
            self._gif.append_data(frame)
            return
        h, w = frame.shape[:2]
        if (h | w) & 1:
            frame = np.pad(frame, ((0, h & 1), (0, w & 1), (0, 0)))
        if self._mp4 is None:
            import imageio_ffmpeg

            self._mp4 = imageio_ffmpeg.write_frames(
                str(self.path), (frame.shape[1], frame.shape[0]), fps=self.fps,
                codec="libx264", pix_fmt_out="yuv420p", macro_block_size=1,
                ffmpeg_log_level="error", output_params=["-f", "mp4"])
            self._mp4.send(None)  # start ffmpeg
        self._mp4.send(np.ascontiguousarray(frame))

    def close(self) -> None:
        if self._gif is not None:
            self._gif.close()
            self._gif = None
        if self._mp4 is not None:
            self._mp4.close()
            self._mp4 = None
