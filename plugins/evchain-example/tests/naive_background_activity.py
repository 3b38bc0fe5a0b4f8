"""Slow, obvious background-activity filter: the reference the kernel is tested against."""

from __future__ import annotations


def background_activity(events, width: int, height: int, window_us: int) -> list[bool]:
    """events: [(x, y, t)] in time order -> keep flags."""
    last = {}  # (x, y) -> time written by the latest neighbouring event
    keep = []
    for x, y, t in events:
        keep.append((x, y) in last and t - last[(x, y)] <= window_us)
        for nx in (x - 1, x, x + 1):
            for ny in (y - 1, y, y + 1):
                if (nx, ny) != (x, y) and 0 <= nx < width and 0 <= ny < height:
                    last[(nx, ny)] = t
    return keep
