"""Slow, obvious edge arrival times (reference for ``evchain.kernels.edge_arrival``)."""

from __future__ import annotations


def arrivals(events, gap_us: int) -> list[int]:
    """events: [(x, y, t, p)] in time order -> for each, the first time of its pixel's run of
    same-polarity events (a run ends at the other polarity or a pause longer than gap_us)."""
    last: dict[tuple[int, int], tuple[int, int, int]] = {}  # pixel -> (t, p, run start)
    out = []
    for x, y, t, p in events:
        prev = last.get((x, y))
        start = t if prev is None or prev[1] != p or t - prev[0] > gap_us else prev[2]
        last[(x, y)] = (t, p, start)
        out.append(start)
    return out
