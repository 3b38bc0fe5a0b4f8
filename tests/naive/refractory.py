"""Slow, obvious refractory filter (reference for ``evchain.kernels.refractory``)."""

from __future__ import annotations


def refractory(events, period_us: int, per_polarity: bool) -> list[bool]:
    """events: [(x, y, t, p)] in time order -> keep flags."""
    last = {}
    keep = []
    for x, y, t, p in events:
        key = (x, y, p > 0) if per_polarity else (x, y)
        ok = key not in last or t - last[key] >= period_us
        if ok:
            last[key] = t
        keep.append(ok)
    return keep
