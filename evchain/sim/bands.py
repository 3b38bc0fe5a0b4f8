"""Frames of a drive at the global frame times, with each band of rows rendered only as often
as its own motion needs (the ``scene`` source's ``band_rows``).

The global times are those of the fastest band (no pixel of it moves more than the source's
``max_motion_px`` between frames). A band is rendered at a global time only if the next global
time would lie beyond its own step (the same rule for :data:`BAND_SPEED_MARGIN` times the
fastest motion of its pixels, from the exact motion field at its last render); in the frames
between two of its renders its rows are the linear interpolation in intensity between them
(:func:`interpolate_band`). A frame is emitted once every band has been rendered at or after
its time, so frames wait in a ring of ``capacity`` frames; when the ring would fill, every
band renders (bounded memory).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from evchain.kernels.scene_bands import interpolate_band
from evchain.sim.drive import Scene

#: a band's step is the frame step for its fastest pixel's speed times this: a band moves at
#: most ``max_motion_px`` / 1.5 between its renders (at 1.0 the events of 0.1 s of the
#: evaluation cell speed-27 differed from whole frames' by a median of 12 µs, at 1.5 by 0)
BAND_SPEED_MARGIN = 1.5


class BandFrames:
    """Frames of ``scene`` with row bands of ``band_rows`` rows rendered at their own steps."""

    def __init__(self, scene: Scene, band_rows: int, capacity: int):
        if band_rows < 1 or capacity < 1:
            raise ValueError(f"band_rows {band_rows} and capacity {capacity} must be >= 1")
        cam = scene.camera
        self.scene = scene
        self.height, self.width = cam.height, cam.width
        self.edges = np.arange(0, self.height + band_rows, band_rows).clip(max=self.height)
        self.edges = np.unique(self.edges)
        self.capacity = capacity
        #: rows rendered and frames emitted so far (the share of pixel rows rendered)
        self.rows_rendered = 0
        self.frames_emitted = 0

    @property
    def nbands(self) -> int:
        return len(self.edges) - 1

    def frames(self, t_us: int, end_us: int, next_dt_us: Callable[[float], int]
               ) -> Iterator[tuple[int, np.ndarray, int]]:
        """(t, frame, dt) for t = t_us, t + dt, ... while t < end_us; ``next_dt_us(v)`` is the
        step after a frame whose fastest pixel moves at v px/s (it must not grow with v)."""
        nb, h, w, cap = self.nbands, self.height, self.width, self.capacity
        edges = self.edges
        ring = np.empty((cap, h, w), np.float32)
        ring_t = np.zeros(cap, np.int64)
        ring_dt = np.zeros(cap, np.int64)
        start = np.empty((h, w), np.float32)      # each band's rows at its last render
        last_t = np.full(nb, -1, np.int64)
        v = np.zeros(nb)
        band_dt = np.zeros(nb, np.int64)
        row_v2 = np.zeros(h)
        band_rows = [np.arange(edges[b], edges[b + 1]) for b in range(nb)]
        head = count = 0
        t = t_us
        while t < end_us:
            slot = (head + count) % cap
            ring_t[slot] = t
            done = np.zeros(nb, bool)
            force = count + 1 == cap        # the ring is full after this frame
            while True:
                dt = next_dt_us(float(v.max()))
                due = ~done & ((last_t < 0) | force | (t + dt >= end_us)
                               | (t + dt > last_t + band_dt))
                if not due.any():
                    break
                due_bands = np.flatnonzero(due)
                rows = np.concatenate([band_rows[b] for b in due_bands])
                self._render_rows(t, ring[slot], rows, row_v2)
                for b in due_bands:
                    v[b] = np.sqrt(row_v2[edges[b]:edges[b + 1]].max())
                    band_dt[b] = next_dt_us(float(v[b]) * BAND_SPEED_MARGIN)
                done |= due
            ring_dt[slot] = dt
            pending = (np.arange(head, head + count) % cap)
            pending_t = ring_t[pending]
            for b in np.flatnonzero(done):
                r0, r1 = edges[b], edges[b + 1]
                if last_t[b] >= 0 and count:
                    between = pending_t > last_t[b]
                    if between.any():
                        interpolate_band(ring, pending[between], pending_t[between], r0, r1,
                                         start, last_t[b], t, slot)
                start[r0:r1] = ring[slot, r0:r1]
            last_t[done] = t
            count += 1
            complete = last_t.min()
            while count and ring_t[head] <= complete:
                self.frames_emitted += 1
                yield int(ring_t[head]), ring[head].copy(), int(ring_dt[head])
                head = (head + 1) % cap
                count -= 1
            t += dt

    def _render_rows(self, t_us: int, out: np.ndarray, rows: np.ndarray,
                     row_v2: np.ndarray) -> None:
        """Render ``rows`` of the frame at t_us into ``out`` (contrast applied) and their speed
        bounds into ``row_v2``; rows spread over the scene's threads."""
        from evchain.kernels.scene_render import render_row_set

        scene = self.scene
        frame, world, _ = scene._frame_args(t_us * 1e-6, out, scene._scratch())
        nt = min(scene._nthreads(), max(1, len(rows) // 8))
        if nt == 1:
            render_row_set(frame, world, out, rows, 0, 1, row_v2)
        else:
            pool = scene._pool_of(scene._nthreads())
            jobs = [pool.submit(render_row_set, frame, world, out, rows, i, nt, row_v2)
                    for i in range(1, nt)]
            render_row_set(frame, world, out, rows, 0, nt, row_v2)
            for job in jobs:
                job.result()
        self.rows_rendered += len(rows)
        if scene.cfg.contrast != 1.0:
            for r0, r1 in _runs(rows):
                scene._contrast(out[r0:r1])


def _runs(rows: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive runs [r0, r1) of the sorted ``rows``."""
    cuts = np.flatnonzero(np.diff(rows) != 1) + 1
    return [(int(p[0]), int(p[-1]) + 1) for p in np.split(rows, cuts)]
