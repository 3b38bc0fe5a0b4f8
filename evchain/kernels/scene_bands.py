"""Numba kernels of the scene's row bands (:mod:`evchain.sim.bands`): the schedule's rule (which
bands render at a frame, their steps, the frames complete), its prediction, and the frames
between two renders of a band, filled by linear interpolation in intensity between them."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit


class StepRule(NamedTuple):
    """The adaptive time step: the fastest pixel moves at most ``max_motion_px`` per step,
    clipped to [``dt_min_us``, ``dt_max_us``]."""

    max_motion_px: float
    dt_min_us: int
    dt_max_us: int


@njit(cache=True, nogil=True)
def step_us(rule, v):
    """The step (µs) after a frame whose fastest pixel moves at v px/s: floor(max_motion_px /
    v) clipped to the rule's bounds; ``dt_max_us`` at rest."""
    if v <= 0.0:
        return np.int64(rule.dt_max_us)
    dt = np.int64(np.floor(rule.max_motion_px / v * 1e6))
    return min(max(dt, np.int64(rule.dt_min_us)), np.int64(rule.dt_max_us))


@njit(cache=True, nogil=True)
def _due(t, dt, end_us, force, last, band_dt, b):
    """Band b renders at t, when the next frame is at t + dt: never rendered, the ring full
    (``force``), t the last frame, or its own step ends before the next frame."""
    return last[b] < 0 or force or t + dt >= end_us or t + dt > last[b] + band_dt[b]


@njit(cache=True, nogil=True)
def plan(t, end_us, force, done, last, band_dt, v, rule, due):
    """The global step after the frame at t (from the fastest band's speed ``v``), returned,
    and in ``due`` the bands that render at t and are not ``done`` yet."""
    dt = step_us(rule, v.max())
    for b in range(done.shape[0]):
        due[b] = not done[b] and _due(t, dt, end_us, force, last, band_dt, b)
    return dt


@njit(cache=True, nogil=True)
def rows_of(bands, edges, rows):
    """The rows of the bands marked in ``bands`` (bands b has rows edges[b] .. edges[b + 1] -
    1) into ``rows``, in order; returns their number."""
    n = 0
    for b in range(bands.shape[0]):
        if bands[b]:
            for r in range(edges[b], edges[b + 1]):
                rows[n] = r
                n += 1
    return n


@njit(cache=True, nogil=True)
def band_steps(due, edges, row_v2, v, band_dt, rule, margin, done):
    """After the ``due`` bands rendered: each one's speed (the square root of its rows'
    largest ``row_v2``) into ``v``, its own step (for ``margin`` times that speed) into
    ``band_dt``, and it is marked ``done``."""
    for b in range(due.shape[0]):
        if due[b]:
            m = row_v2[edges[b]]
            for r in range(edges[b] + 1, edges[b + 1]):
                m = max(m, row_v2[r])
            v[b] = np.sqrt(m)
            band_dt[b] = step_us(rule, v[b] * margin)
            done[b] = True


@njit(cache=True, nogil=True)
def settle(ring, ring_t, head, count, slot, t, done, last, edges, start):
    """The frame at t (ring slot ``slot``; ``count`` frames wait before it from ``head``) is
    rendered where ``done``: each done band's rows are filled in the waiting frames since its
    last render (:func:`interpolate_band`) and kept as its start, and its last render is t.
    Returns how many frames from ``head`` are complete (every band rendered at or after
    them)."""
    cap = ring.shape[0]
    slots = np.empty(count, np.int64)
    times = np.empty(count, np.int64)
    for b in range(done.shape[0]):
        if not done[b]:
            continue
        r0 = edges[b]
        r1 = edges[b + 1]
        if last[b] >= 0:
            m = 0
            for i in range(count):
                s = (head + i) % cap
                if ring_t[s] > last[b]:
                    slots[m] = s
                    times[m] = ring_t[s]
                    m += 1
            if m:
                interpolate_band(ring, slots[:m], times[:m], r0, r1, start, last[b], t, slot)
        for r in range(r0, r1):
            for x in range(ring.shape[2]):
                start[r, x] = ring[slot, r, x]
        last[b] = t
    complete = last.min()
    n = 0
    while n < count + 1 and ring_t[(head + n) % cap] <= complete:
        n += 1
    return n


@njit(cache=True, nogil=True)
def predict(t, dt, end_us, cap, waiting, last, band_dt, masks):
    """The bands that render at t, t + dt, ... (``masks.shape[0]`` frames, before end_us) if
    no speed changed, as the schedule decides them (``waiting``: the times of the frames in
    the ring, not yet complete); returns how many frames were predicted."""
    nb = last.shape[0]
    lst = last.copy()
    wait = np.empty(waiting.shape[0] + masks.shape[0], np.int64)
    wait[:waiting.shape[0]] = waiting
    w0 = 0
    w1 = waiting.shape[0]
    k = 0
    while k < masks.shape[0] and t < end_us:
        force = w1 - w0 + 1 == cap
        for b in range(nb):
            masks[k, b] = _due(t, dt, end_us, force, lst, band_dt, b)
        for b in range(nb):
            if masks[k, b]:
                lst[b] = t
        wait[w1] = t
        w1 += 1
        complete = lst.min()
        while w0 < w1 and wait[w0] <= complete:
            w0 += 1
        t += dt
        k += 1
    return k


@njit(cache=True, error_model="numpy", nogil=True)
def interpolate_band(ring, slots, times, r0, r1, start, t0, t1, end_slot):
    """Fill rows ``r0:r1`` of the frames ``ring[slots[i]]`` (at ``times[i]``, t0 < times[i] <
    t1) with ``a + w (b - a)``, w = (times[i] - t0) / (t1 - t0), a = ``start[r0:r1]`` (the rows
    rendered at t0) and b = ``ring[end_slot, r0:r1]`` (rendered at t1); all float32 (w
    rounded to float32 first)."""
    w_ = ring.shape[2]
    span = float(t1 - t0)
    for i in range(slots.shape[0]):
        s = slots[i]
        w = np.float32((times[i] - t0) / span)
        for j in range(r0, r1):
            for x in range(w_):
                a = start[j, x]
                ring[s, j, x] = a + w * (ring[end_slot, j, x] - a)
