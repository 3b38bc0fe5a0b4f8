"""Event timing error against exact crossing times (emulator validation).

The k-th event of each pixel and polarity is matched with the k-th true crossing of that pixel
and polarity; unmatched events on either side count in ``count_diff``.
"""

from __future__ import annotations

import numpy as np


def _ranked_keys(x, y, p, t, width: int):
    """Per event: group key (pixel, polarity) and rank within the group (time order)."""
    x = np.asarray(x, np.int64)
    y = np.asarray(y, np.int64)
    pol = (np.asarray(p) > 0).astype(np.int64)
    group = (y * width + x) * 2 + pol
    order = np.lexsort((np.asarray(t), group))
    g = group[order]
    n = len(g)
    if n == 0:
        return np.zeros(0, np.int64), order
    first = np.r_[True, g[1:] != g[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(n), 0))
    rank = np.arange(n) - start
    return g * (1 << 24) + rank, order


def timing_errors(events_x, events_y, events_p, events_t, truth: np.ndarray,
                  width: int) -> dict[str, float | int]:
    """Match events (x, y, p, t in µs, int or float) with ``truth`` (structured x, y, t, p).

    Returns ``n_events``, ``n_truth``, ``n_matched``, ``count_diff`` (events - truth),
    ``unmatched`` (on both sides) and ``median_abs_dt_us``, ``p95_abs_dt_us``,
    ``max_abs_dt_us``, ``mean_dt_us`` (signed, event - truth) over matched pairs.
    """
    et = np.asarray(events_t, np.float64)
    ke, oe = _ranked_keys(events_x, events_y, events_p, et, width)
    kt, ot = _ranked_keys(truth["x"], truth["y"], truth["p"], truth["t"], width)
    _, ie, it = np.intersect1d(ke, kt, assume_unique=True, return_indices=True)
    dt = et[oe[ie]] - np.asarray(truth["t"], np.float64)[ot[it]]
    ad = np.abs(dt)
    m = len(dt)
    nan = float("nan")
    return {
        "n_events": int(len(et)), "n_truth": int(len(truth)), "n_matched": int(m),
        "count_diff": int(len(et) - len(truth)),
        "unmatched": int(len(et) - m + len(truth) - m),
        "median_abs_dt_us": float(np.median(ad)) if m else nan,
        "p95_abs_dt_us": float(np.percentile(ad, 95)) if m else nan,
        "max_abs_dt_us": float(ad.max()) if m else nan,
        "mean_dt_us": float(dt.mean()) if m else nan,
    }
