"""Slow references of the scene's band and tile kernels (evchain/kernels/scene_bands.py)."""

from __future__ import annotations

import numpy as np


def interpolate_tiles(ring, slots, times, done, last_t, redges, cedges, start, t1, end_slot):
    """Each done tile of ring[s] for s in slots with a time after the tile's last render t0
    (if any): start + w (end - start), w = (t - t0)/(t1 - t0) rounded to float32, in float32;
    then the tile of ring[end_slot] copied into start."""
    for b, c in zip(*np.nonzero(done), strict=True):
        tile = (slice(redges[b], redges[b + 1]), slice(cedges[c], cedges[c + 1]))
        t0 = last_t[b, c]
        a = start[tile].astype(np.float32)
        e = ring[end_slot][tile].astype(np.float32)
        if t0 >= 0:
            for s, t in zip(slots, times, strict=True):
                if t > t0:
                    w = np.float32((t - t0) / float(t1 - t0))
                    ring[s][tile] = a + w * (e - a)
        start[tile] = e
    return ring, start
