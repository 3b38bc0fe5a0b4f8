"""Numba kernel of the scene's row bands (:mod:`evchain.sim.bands`): the frames between two
renders of a band, filled by linear interpolation in intensity between them."""

from __future__ import annotations

import numpy as np
from numba import njit


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
