"""Slow, obvious AEDAT 2.0 record decoding and encoding, one record at a time (reference for
``evchain.kernels.aedat2``)."""

from __future__ import annotations

import struct


def decode(data: bytes, layout: str, width: int, height: int):
    """Records -> (events [(x, y, raw_t, p)], skipped, first bad record index or None)."""
    events, skipped = [], 0
    for i in range(len(data) // 8):
        addr, ts = struct.unpack(">II", data[8 * i:8 * i + 8])
        if layout == "davis":
            if addr >> 31 or (addr >> 10) & 1:  # APS/IMU, or external-input special event
                skipped += 1
                continue
            xr, yr, on = (addr >> 12) & 1023, (addr >> 22) & 511, (addr >> 11) & 1
        else:
            if addr >> 16:
                return events, skipped, i
            if (addr >> 15) & 1:
                skipped += 1
                continue
            xr, yr, on = (addr >> 1) & 127, (addr >> 8) & 127, 1 - (addr & 1)
        if xr >= width or yr >= height:
            return events, skipped, i
        events.append((width - 1 - xr, height - 1 - yr, ts, 1 if on else -1))
    return events, skipped, None


def encode(events, layout: str, width: int, height: int) -> bytes:
    """[(x, y, t, p)] -> record bytes."""
    out = b""
    for x, y, t, p in events:
        xr, yr, on = width - 1 - x, height - 1 - y, 1 if p > 0 else 0
        if layout == "davis":
            addr = (yr << 22) | (xr << 12) | (on << 11)
        else:
            addr = (yr << 8) | (xr << 1) | (1 - on)
        out += struct.pack(">II", addr, t % (1 << 32))
    return out
