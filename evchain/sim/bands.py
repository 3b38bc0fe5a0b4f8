"""Frames of a drive at the global frame times, with each tile (a band of rows, or a block of
columns of one) rendered only as often as its own motion needs (the ``scene`` source's
``band_rows`` and ``band_cols``).

The global times are those of the fastest tile (no pixel of it moves more than the source's
``max_motion_px`` between frames). A tile is rendered at a global time only if the next global
time would lie beyond its own step (the same rule for :data:`BAND_SPEED_MARGIN` times the
fastest motion of its pixels, from the exact motion field at its last render); in the frames
between two of its renders its pixels are the linear interpolation in intensity between them
(:func:`interpolate_tiles`). A frame is emitted once every tile has been rendered at or after
its time, so frames wait in a ring of ``capacity`` frames; when the ring would fill, every
tile renders (bounded memory).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from evchain.kernels.scene_bands import interpolate_tiles
from evchain.sim.drive import Scene

#: a tile's step is the frame step for its fastest pixel's speed times this: a tile moves at
#: most ``max_motion_px`` / 1.5 between its renders (at 1.0 the events of 0.1 s of the
#: evaluation cell speed-27 differed from whole frames' by a median of 12 µs, at 1.5 by 0)
BAND_SPEED_MARGIN = 1.5


class BandFrames:
    """Frames of ``scene`` with tiles of ``band_rows`` rows by ``band_cols`` columns (0: whole
    rows, row bands) rendered at their own steps; the last tile of a row or column is shorter
    when the size does not divide the image's."""

    def __init__(self, scene: Scene, band_rows: int, capacity: int, band_cols: int = 0):
        if band_rows < 1 or capacity < 1 or band_cols < 0:
            raise ValueError(f"band_rows {band_rows} and capacity {capacity} must be >= 1, "
                             f"band_cols {band_cols} >= 0")
        cam = scene.camera
        self.scene = scene
        self.height, self.width = cam.height, cam.width
        self.tile_cols = band_cols or self.width
        self.edges = _edges(self.height, band_rows)         # rows of band b: edges[b:b + 2]
        self.col_edges = _edges(self.width, self.tile_cols)
        self.capacity = capacity
        #: pixels rendered and frames emitted so far (the share of pixels rendered)
        self.pixels_rendered = 0
        self.frames_emitted = 0

    @property
    def nbands(self) -> int:
        return len(self.edges) - 1

    @property
    def shape(self) -> tuple[int, int]:
        """Tiles per column and per row of the image."""
        return len(self.edges) - 1, len(self.col_edges) - 1

    def frames(self, t_us: int, end_us: int, next_dt_us: Callable
               ) -> Iterator[tuple[int, np.ndarray, int]]:
        """(t, frame, dt) for t = t_us, t + dt, ... while t < end_us; ``next_dt_us(v)`` is the
        step after a frame whose fastest pixel moves at v px/s (it must not grow with v; for
        a float array of speeds it returns the int64 array of steps)."""
        (nb, nc), h, w, cap = self.shape, self.height, self.width, self.capacity
        ring = np.empty((cap, h, w), np.float32)
        ring_t = np.zeros(cap, np.int64)
        ring_dt = np.zeros(cap, np.int64)
        start = np.empty((h, w), np.float32)      # each tile's pixels at its last render
        last_t = np.full((nb, nc), -1, np.int64)
        v = np.zeros((nb, nc))
        tile_dt = np.zeros((nb, nc), np.int64)
        v2 = np.zeros((h, nc))                   # per row and tile: squared speed bound
        head = count = 0
        t = t_us
        while t < end_us:
            slot = (head + count) % cap
            ring_t[slot] = t
            done = np.zeros((nb, nc), bool)
            force = count + 1 == cap        # the ring is full after this frame
            while True:
                dt = int(next_dt_us(float(v.max())))
                due = ~done & ((last_t < 0) | force | (t + dt >= end_us)
                               | (t + dt > last_t + tile_dt))
                if not due.any():
                    break
                self._render_spans(t, ring[slot], *self._spans(due), v2)
                band_v2 = np.maximum.reduceat(v2, self.edges[:-1], axis=0)
                v[due] = np.sqrt(band_v2[due])
                tile_dt[due] = next_dt_us(v[due] * BAND_SPEED_MARGIN)
                done |= due
            ring_dt[slot] = dt
            pending = np.arange(head, head + count) % cap
            interpolate_tiles(ring, pending, ring_t[pending], done, last_t, self.edges,
                              self.col_edges, start, t, slot)
            last_t[done] = t
            count += 1
            complete = last_t.min()
            while count and ring_t[head] <= complete:
                self.frames_emitted += 1
                yield int(ring_t[head]), ring[head].copy(), int(ring_dt[head])
                head = (head + 1) % cap
                count -= 1
            t += dt

    def _spans(self, due: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, x0s, x1s) of the pieces of rows to render for the ``due`` tiles: each run of
        due tiles next to each other in a band is one column range, rendered in each of the
        band's rows (run by run, rows in order within a run)."""
        nb, nc = due.shape
        padded = np.zeros((nb, nc + 2), np.int8)
        padded[:, 1:-1] = due
        step = np.diff(padded, axis=1)
        band, c0 = np.nonzero(step == 1)          # runs, band by band, left to right
        c1 = np.nonzero(step == -1)[1]
        first = self.edges[band]
        nrows = self.edges[band + 1] - first
        ends = np.cumsum(nrows)
        rows = np.repeat(first - (ends - nrows), nrows) + np.arange(ends[-1])
        return (rows, np.repeat(self.col_edges[c0], nrows),
                np.repeat(self.col_edges[c1], nrows))

    def _render_spans(self, t_us: int, out: np.ndarray, rows: np.ndarray, x0s: np.ndarray,
                      x1s: np.ndarray, v2: np.ndarray) -> None:
        """Render columns [x0s[i], x1s[i]) of rows[i] of the frame at t_us into ``out``
        (contrast applied) and their tiles' speed bounds into ``v2``; spans spread over the
        scene's threads."""
        from evchain.kernels.scene_render import render_spans

        scene = self.scene
        frame, world, _ = scene._frame_args(t_us * 1e-6, out, scene._scratch())
        args = (frame, world, out, rows, x0s, x1s, self.tile_cols)
        nt = min(scene._nthreads(), max(1, len(rows) // 8))
        if nt == 1:
            render_spans(*args, 0, 1, v2)
        else:
            pool = scene._pool_of(scene._nthreads())
            jobs = [pool.submit(render_spans, *args, i, nt, v2) for i in range(1, nt)]
            render_spans(*args, 0, nt, v2)
            for job in jobs:
                job.result()
        self.pixels_rendered += int((x1s - x0s).sum())
        if scene.cfg.contrast != 1.0:       # by rectangles: runs of rows with one range
            cut = (np.diff(rows) != 1) | (np.diff(x0s) != 0) | (np.diff(x1s) != 0)
            firsts = np.concatenate([[0], np.flatnonzero(cut) + 1])
            lasts = np.concatenate([firsts[1:], [len(rows)]]) - 1
            for i, e in zip(firsts, lasts, strict=True):
                scene._contrast(out[rows[i]:rows[e] + 1, x0s[i]:x1s[i]])


def _edges(n: int, size: int) -> np.ndarray:
    """Edges 0, size, 2 size, ..., n of pieces of ``size`` (the last one shorter)."""
    return np.unique(np.arange(0, n + size, size).clip(max=n)).astype(np.int64)
