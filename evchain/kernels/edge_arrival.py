"""Edge arrival times: when each event's pixel began its current run of same-polarity events.

State per pixel: the last event's time and polarity, and the start of its current run. A run
ends at an event of the other polarity or after a pause longer than ``gap_us``. Python API:
:class:`evchain.core.edge_arrival.EdgeArrivals`.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def new_state(height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(last time µs, last polarity, run start µs) per pixel; no event seen yet."""
    return (np.full((height, width), np.iinfo(np.int64).min // 2, np.int64),
            np.zeros((height, width), np.int8),
            np.zeros((height, width), np.int64))


@njit(cache=True, nogil=True)
def arrivals(x, y, t, p, last_t, last_p, start, gap_us, out):
    """``out[i]``: the start of event i's pixel's run of same-polarity events, event i's
    included (its own time when it starts one). The state arrays are updated in place."""
    for i in range(t.shape[0]):
        yi = y[i]
        xi = x[i]
        ti = t[i]
        if last_p[yi, xi] != p[i] or ti - last_t[yi, xi] > gap_us:
            start[yi, xi] = ti
        out[i] = start[yi, xi]
        last_t[yi, xi] = ti
        last_p[yi, xi] = p[i]
