"""Per-pixel refractory (dead-time) filter kernel (numba)."""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def refractory(x, y, t, p, last, period_us, per_polarity, keep):
    """Mark in ``keep`` the events that come at least ``period_us`` after the last *passed*
    event of their pixel (and polarity, if ``per_polarity``); update ``last`` ([C, H, W] int64,
    C = 2 with ``per_polarity`` else 1; channel 1 is ON). Returns the number kept."""
    n = x.shape[0]
    k = 0
    for i in range(n):
        c = 0
        if per_polarity and p[i] > 0:
            c = 1
        ti = t[i]
        if ti - last[c, y[i], x[i]] >= period_us:
            last[c, y[i], x[i]] = ti
            keep[i] = True
            k += 1
        else:
            keep[i] = False
    return k
