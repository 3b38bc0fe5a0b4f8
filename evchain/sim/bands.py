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

With more than one render thread, the schedule is predicted :data:`AHEAD` frames on, with
every band's speed as at its last render, and the bands each predicted frame needs render
on the scene's threads meanwhile (:class:`_Ahead`). The schedule itself is decided as
without: a predicted render is used only where the schedule asks for those rows at that
time, and the others are dropped, so the frames do not depend on the threads. Where the
global step keeps changing (the obstacle near, its image speeding up from frame to frame)
the predicted times miss: after a frame that had no render ahead the predictions pause (for
``AHEAD`` frames, doubling while they keep missing) and each frame's rows are split over the
threads instead, so that the threads do not render frames nobody asks for.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future

import numpy as np

from evchain.kernels.scene_bands import (
    StepRule,
    band_steps,
    plan,
    predict,
    rows_of,
    settle,
)
from evchain.sim.drive import Scene

#: a band's step is the frame step for its fastest pixel's speed times this: a band moves at
#: most ``max_motion_px`` / 1.5 between its renders (at 1.0 the events of 0.1 s of the
#: evaluation cell speed-27 differed from whole frames' by a median of 12 µs, at 1.5 by 0)
BAND_SPEED_MARGIN = 1.5
#: frames whose renders are predicted and started ahead of the schedule (threads > 1)
AHEAD = 8
#: the longest pause of the predictions after they missed, in frames
MAX_PAUSE = 256


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
        self._ahead: _Ahead | None = None

    @property
    def nbands(self) -> int:
        return len(self.edges) - 1

    def frames(self, t_us: int, end_us: int, rule: StepRule
               ) -> Iterator[tuple[int, np.ndarray, int]]:
        """(t, frame, dt) for t = t_us, t + dt, ... while t < end_us, the steps by ``rule``."""
        nb, h, w, cap = self.nbands, self.height, self.width, self.capacity
        edges = self.edges.astype(np.int64)
        ring = np.empty((cap, h, w), np.float32)
        ring_t = np.zeros(cap, np.int64)
        ring_dt = np.zeros(cap, np.int64)
        start = np.empty((h, w), np.float32)      # each band's rows at its last render
        last_t = np.full(nb, -1, np.int64)
        v = np.zeros(nb)
        band_dt = np.zeros(nb, np.int64)
        row_v2 = np.zeros(h)
        rows = np.empty(h, np.int64)
        done = np.zeros(nb, bool)
        due = np.zeros(nb, bool)
        self._ahead = _Ahead(self.scene, h, w, edges) if self.scene._nthreads() > 1 else None
        head = count = 0
        t = t_us
        try:
            while t < end_us:
                slot = (head + count) % cap
                ring_t[slot] = t
                done[:] = False
                force = count + 1 == cap        # the ring is full after this frame
                while True:
                    dt = plan(t, end_us, force, done, last_t, band_dt, v, rule, due)
                    n = rows_of(due, edges, rows)
                    if n == 0:
                        break
                    self._render_rows(t, ring[slot], rows[:n], row_v2)
                    band_steps(due, edges, row_v2, v, band_dt, rule, BAND_SPEED_MARGIN, done)
                ring_dt[slot] = dt
                n_out = settle(ring, ring_t, head, count, slot, t, done, last_t, edges, start)
                count += 1
                if self._ahead is not None and self._ahead.predicting():
                    waiting = ring_t[np.arange(head + n_out, head + count) % cap]
                    self._ahead.predict(t + dt, dt, end_us, cap, waiting, last_t, band_dt)
                for _ in range(n_out):
                    self.frames_emitted += 1
                    yield int(ring_t[head]), ring[head].copy(), int(ring_dt[head])
                    head = (head + 1) % cap
                    count -= 1
                t += dt
        finally:
            if self._ahead is not None:
                self._ahead.close()
                self._ahead = None

    def _render_rows(self, t_us: int, out: np.ndarray, rows: np.ndarray,
                     row_v2: np.ndarray) -> None:
        """Render ``rows`` of the frame at t_us into ``out`` (contrast applied) and their speed
        bounds into ``row_v2``: from the renders started ahead where they hold these rows,
        the rest here (with one thread) or spread over the scene's threads."""
        from evchain.kernels.scene_render import render_row_set

        scene = self.scene
        ahead = self._ahead
        todo = rows if ahead is None else ahead.take(t_us, out, rows, row_v2)
        if len(todo):
            frame, world, _ = scene._frame_args(t_us * 1e-6, out, scene._scratch())
            nt = (1 if ahead is not None and ahead.predicting()
                  else min(scene._nthreads(), max(1, len(todo) // 8)))
            if nt == 1:
                render_row_set(frame, world, out, todo, 0, 1, row_v2)
            else:
                pool = scene._pool_of(scene._nthreads())
                jobs = [pool.submit(render_row_set, frame, world, out, todo, i, nt, row_v2)
                        for i in range(1, nt)]
                render_row_set(frame, world, out, todo, 0, nt, row_v2)
                for job in jobs:
                    job.result()
        self.rows_rendered += len(rows)
        if scene.cfg.contrast != 1.0:
            for r0, r1 in _runs(rows):
                scene._contrast(out[r0:r1])


class _Ahead:
    """Renders of the frames the schedule is predicted to need next, on the scene's threads.

    :meth:`predict` runs the schedule's rule :data:`AHEAD` frames on from the current state,
    every band's step and the global step as they are now, and starts a render of each
    predicted frame's due rows that is not already under way (a render predicted with other
    rows is replaced). :meth:`take` hands the schedule the rows it asks for at a time from
    that time's render, if any; renders of earlier times are dropped. A time predicted
    for and not asked for, or asked for and not predicted, is a miss: the predictions pause
    (:meth:`predicting` false) for ``AHEAD`` frames, twice as long after each further miss
    (at most :data:`MAX_PAUSE`), and the pause ends the count of misses once a prediction
    holds again."""

    def __init__(self, scene: Scene, height: int, width: int, edges: np.ndarray):
        self.scene = scene
        self.edges = edges
        self.masks = np.zeros((AHEAD, len(edges) - 1), bool)
        self.pool = scene._pool_of(scene._nthreads())
        self.shape = (height, width)
        #: time -> (the bands rendered, future, frame, row_v2)
        self.jobs: dict[int, tuple[np.ndarray, Future, np.ndarray, np.ndarray]] = {}
        self.free: list[tuple[np.ndarray, np.ndarray]] = []
        self.pause = 0          # frames left without predictions
        self.misses = 0         # misses in a row
        self.asked = -1         # the last time asked for

    def predicting(self) -> bool:
        """Whether predictions run (not paused after misses)."""
        return self.pause == 0

    def predict(self, t: int, dt: int, end_us: int, cap: int, waiting: np.ndarray,
                last_t: np.ndarray, band_dt: np.ndarray) -> None:
        """Start the renders of the frames at t, t + dt, ... (``AHEAD`` of them, before
        end_us) as the schedule would make them if no band's speed changed; ``waiting``: the
        times of the frames in the ring, not yet complete."""
        n = predict(t, dt, end_us, cap, waiting, last_t, band_dt, self.masks)
        for k in range(n):
            tk = t + k * dt
            due = self.masks[k]
            job = self.jobs.get(tk)
            if job is None or not np.array_equal(job[0], due):
                if job is not None:
                    self._drop(self.jobs.pop(tk))
                if due.any():       # a frame that renders nothing needs no job
                    self.jobs[tk] = self._start(tk, due.copy())

    def _start(self, t: int, bands: np.ndarray):
        from evchain.kernels.scene_render import render_row_set

        frame, v2 = self.free.pop() if self.free else (np.empty(self.shape, np.float32),
                                                       np.zeros(self.shape[0]))
        rows = np.empty(self.shape[0], np.int64)
        rows = rows[:rows_of(bands, self.edges, rows)]
        scene = self.scene

        def render() -> None:
            args = scene._frame_args(t * 1e-6, frame, scene._scratch())
            render_row_set(*args, rows, 0, 1, v2)

        return bands, self.pool.submit(render), frame, v2

    def _drop(self, job) -> None:
        """Forget a render; its buffers are reused only if it never started."""
        if job[1].cancel():
            self.free.append((job[2], job[3]))

    def take(self, t: int, out: np.ndarray, rows: np.ndarray, row_v2: np.ndarray
             ) -> np.ndarray:
        """Copy the rows of ``rows`` rendered ahead at t into ``out`` and their bounds into
        ``row_v2``; returns the rows still to render."""
        stale = [tj for tj in self.jobs if tj < t]
        for tj in stale:
            self._drop(self.jobs.pop(tj))
        job = self.jobs.pop(t, None)
        if t != self.asked:      # a frame's first rows (more can follow as speeds change)
            self.asked = t
            if self.pause:
                self.pause -= 1
            elif job is None or stale:
                self.pause = min(MAX_PAUSE, AHEAD << min(self.misses, 5))
                self.misses += 1
            else:
                self.misses = 0
        if job is None:
            return rows
        bands, future, frame, v2 = job
        future.result()
        have = bands[np.searchsorted(self.edges, rows, side="right") - 1]
        got = rows[have]
        out[got] = frame[got]
        row_v2[got] = v2[got]
        self.free.append((frame, v2))
        return rows[~have]

    def close(self) -> None:
        for job in self.jobs.values():
            job[1].cancel()
        self.jobs.clear()


def _runs(rows: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive runs [r0, r1) of the sorted ``rows``."""
    cuts = np.flatnonzero(np.diff(rows) != 1) + 1
    return [(int(p[0]), int(p[-1]) + 1) for p in np.split(rows, cuts)]
