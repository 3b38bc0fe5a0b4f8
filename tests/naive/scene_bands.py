"""Slow references of the scene's row-band kernels (evchain/kernels/scene_bands.py)."""

from __future__ import annotations

import numpy as np


def interpolate_band(ring, slots, times, r0, r1, start, t0, t1, end_slot):
    """Rows r0:r1 of ring[s] for s in slots: start + w (end - start), w = (t - t0)/(t1 - t0)
    rounded to float32, in float32."""
    a = start[r0:r1].astype(np.float32)
    b = ring[end_slot, r0:r1].astype(np.float32)
    for s, t in zip(slots, times, strict=True):
        w = np.float32((t - t0) / float(t1 - t0))
        ring[s, r0:r1] = a + w * (b - a)
    return ring


def step_us(max_motion_px, dt_min, dt_max, v):
    """The adaptive step (µs) after a frame whose fastest pixel moves at v px/s."""
    if v <= 0:
        return dt_max
    return int(min(max(int(np.floor(max_motion_px / v * 1e6)), dt_min), dt_max))


def due(t, dt, end_us, force, last, band_dt):
    """Bands that render at t when the next frame is at t + dt."""
    return (last < 0) | force | (t + dt >= end_us) | (t + dt > last + band_dt)


def band_frames(render_rows, h, w, edges, cap, t_us, end_us, step, margin=1.5):
    """The row bands' schedule written plainly: (t, frame, dt) of every frame and the renders
    (t, rows) it asks ``render_rows(t, out, rows, row_v2)`` for; ``step(v)`` is the step rule."""
    nb = len(edges) - 1
    ring = np.empty((cap, h, w), np.float32)
    ring_t = np.zeros(cap, np.int64)
    ring_dt = np.zeros(cap, np.int64)
    start = np.empty((h, w), np.float32)
    last_t = np.full(nb, -1, np.int64)
    v = np.zeros(nb)
    band_dt = np.zeros(nb, np.int64)
    row_v2 = np.zeros(h)
    out, renders = [], []
    head = count = 0
    t = t_us
    while t < end_us:
        slot = (head + count) % cap
        ring_t[slot] = t
        done = np.zeros(nb, bool)
        force = count + 1 == cap
        while True:
            dt = step(float(v.max()))
            d = ~done & due(t, dt, end_us, force, last_t, band_dt)
            if not d.any():
                break
            rows = np.concatenate([np.arange(edges[b], edges[b + 1]) for b in np.flatnonzero(d)])
            render_rows(t, ring[slot], rows, row_v2)
            renders.append((int(t), [int(r) for r in rows]))
            for b in np.flatnonzero(d):
                v[b] = np.sqrt(row_v2[edges[b]:edges[b + 1]].max())
                band_dt[b] = step(float(v[b]) * margin)
            done |= d
        ring_dt[slot] = dt
        pending = np.arange(head, head + count) % cap
        for b in np.flatnonzero(done):
            r0, r1 = edges[b], edges[b + 1]
            if last_t[b] >= 0:
                between = pending[ring_t[pending] > last_t[b]]
                interpolate_band(ring, between, ring_t[between], r0, r1, start, last_t[b], t,
                                 slot)
            start[r0:r1] = ring[slot, r0:r1]
        last_t[done] = t
        count += 1
        while count and ring_t[head] <= last_t.min():
            out.append((int(ring_t[head]), ring[head].copy(), int(ring_dt[head])))
            head = (head + 1) % cap
            count -= 1
        t += dt
    return out, renders


def predict(t, dt, end_us, cap, waiting, last, band_dt, n):
    """The due bands of the next n frames from t if no speed changes (the schedule's rule,
    frame by frame)."""
    last = last.copy()
    waiting = list(waiting)
    masks = []
    while len(masks) < n and t < end_us:
        d = due(t, dt, end_us, len(waiting) + 1 == cap, last, band_dt)
        masks.append(d)
        last[d] = t
        waiting.append(t)
        while waiting and waiting[0] <= last.min():
            waiting.pop(0)
        t += dt
    return np.array(masks, bool).reshape(len(masks), len(last))
