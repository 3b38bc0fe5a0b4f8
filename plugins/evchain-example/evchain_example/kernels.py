"""numba kernel of the background-activity filter.

The slow reference it is tested against is tests/naive_background_activity.py.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True)
def background_activity(x, y, t, last, window_us, keep):
    """``keep[i]`` iff ``t[i] - last[y, x] <= window_us``; then write ``t[i]`` into the 8
    neighbours of (x, y) in ``last`` ([H, W] int64). Returns the number kept."""
    h, w = last.shape
    k = 0
    for i in range(x.shape[0]):
        xi = int(x[i])
        yi = int(y[i])
        ti = t[i]
        ok = ti - last[yi, xi] <= window_us
        keep[i] = ok
        if ok:
            k += 1
        for dy in range(-1, 2):
            yy = yi + dy
            if yy < 0 or yy >= h:
                continue
            for dx in range(-1, 2):
                xx = xi + dx
                if (dx == 0 and dy == 0) or xx < 0 or xx >= w:
                    continue
                last[yy, xx] = ti
    return k
