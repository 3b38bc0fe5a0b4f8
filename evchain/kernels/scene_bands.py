"""Numba kernel of the scene's bands and tiles (:mod:`evchain.sim.bands`): the frames between
two renders of a tile, filled by linear interpolation in intensity between them."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy", nogil=True)
def interpolate_tiles(ring, slots, times, done, last_t, redges, cedges, start, t1, end_slot):
    """For every tile (b, c) with ``done[b, c]`` (rows ``redges[b]:redges[b + 1]``, columns
    ``cedges[c]:cedges[c + 1]``), just rendered into ``ring[end_slot]`` at t1: if it rendered
    before (t0 = ``last_t[b, c]`` >= 0), fill it in the frames ``ring[slots[i]]`` with
    ``times[i]`` > t0 (and < t1) with ``a + w (b - a)``, w = (times[i] - t0) / (t1 - t0)
    rounded to float32, a = ``start``'s tile (rendered at t0), b = ``ring[end_slot]``'s; then
    copy ``ring[end_slot]``'s tile into ``start``. All float32."""
    for b in range(done.shape[0]):
        r0 = redges[b]
        r1 = redges[b + 1]
        for c in range(done.shape[1]):
            if not done[b, c]:
                continue
            x0 = cedges[c]
            x1 = cedges[c + 1]
            t0 = last_t[b, c]
            if t0 >= 0:
                span = float(t1 - t0)
                for i in range(slots.shape[0]):
                    if times[i] <= t0:
                        continue
                    s = slots[i]
                    w = np.float32((times[i] - t0) / span)
                    for j in range(r0, r1):
                        for x in range(x0, x1):
                            a = start[j, x]
                            ring[s, j, x] = a + w * (ring[end_slot, j, x] - a)
            for j in range(r0, r1):
                for x in range(x0, x1):
                    start[j, x] = ring[end_slot, j, x]
