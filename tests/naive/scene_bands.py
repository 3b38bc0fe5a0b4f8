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
