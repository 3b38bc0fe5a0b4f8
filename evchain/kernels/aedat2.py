"""AEDAT 2.0 record decoding and encoding in one pass (numba).

Records are pairs of big-endian uint32 (address, timestamp). The kernels take the bytes viewed as
native little-endian uint32 ``words`` (``np.frombuffer(buf, "<u4")``, no copy) and swap bytes
themselves. ``layout`` 0 is the DAVIS layout, 1 is DVS128 (see ``evchain.io.aedat2``).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _bswap(v):
    return (((v & np.uint32(0xFF)) << np.uint32(24)) | ((v & np.uint32(0xFF00)) << np.uint32(8))
            | ((v >> np.uint32(8)) & np.uint32(0xFF00)) | (v >> np.uint32(24)))


@njit(cache=True, nogil=True)
def decode(words, layout, width, height, offset, last_t, x, y, t, p):
    """Decode ``len(words) // 2`` records into the DVS events' ``x, y`` (evchain top-left),
    ``t = raw timestamp + offset`` (int64) and ``p`` (±1), skipping non-DVS records.

    Returns ``(n_events, bad_record, first_backstep, n_skipped)``: ``bad_record`` is the record
    index of the first address outside the sensor (or of an address that does not fit the DVS128
    layout) and stops decoding, -1 if none; ``first_backstep`` is the index (among the events) of
    the first event whose ``t`` is below the previous one (the one before the chunk is ``last_t``;
    pass a very small value for the first chunk), -1 if none.
    """
    n_rec = words.shape[0] // 2
    k = 0
    skipped = 0
    back = -1
    prev = last_t
    wm1 = np.uint32(width - 1)
    hm1 = np.uint32(height - 1)
    for i in range(n_rec):
        a = _bswap(words[2 * i])
        if layout == 0:
            if a & np.uint32(0x80000400):
                skipped += 1
                continue
            xr = (a >> np.uint32(12)) & np.uint32(0x3FF)
            yr = a >> np.uint32(22)
            on = (a >> np.uint32(11)) & np.uint32(1)
        else:
            high = a >> np.uint32(15)
            if high != 0:
                if high == 1:
                    skipped += 1
                    continue
                return k, i, back, skipped
            xr = (a >> np.uint32(1)) & np.uint32(0x7F)
            yr = (a >> np.uint32(8)) & np.uint32(0x7F)
            on = (a & np.uint32(1)) ^ np.uint32(1)
        if xr > wm1 or yr > hm1:
            return k, i, back, skipped
        ts = np.int64(_bswap(words[2 * i + 1])) + offset
        if ts < prev and back < 0:
            back = k
        prev = ts
        x[k] = np.uint16(wm1 - xr)
        y[k] = np.uint16(hm1 - yr)
        t[k] = ts
        p[k] = np.int8(2 * np.int64(on) - 1)
        k += 1
    return k, -1, back, skipped


@njit(cache=True, nogil=True)
def encode(x, y, t, p, layout, width, height, prev_t, words):
    """Write events as records into ``words`` (``2 n`` uint32 whose bytes are big-endian).

    Returns ``(bad, gap)``: the index of the first event outside the sensor (nothing is written
    from it on) or -1, and the index of the first event at least 2**31 µs after its predecessor
    (``prev_t`` before the first) or -1. Timestamps are written modulo 2**32.
    """
    n = x.shape[0]
    gap = -1
    prev = prev_t
    for i in range(n):
        if t[i] - prev >= np.int64(1) << np.int64(31) and gap < 0:
            gap = i
        prev = t[i]
        xv = np.uint32(x[i])
        yv = np.uint32(y[i])
        if xv >= width or yv >= height:
            return i, gap
        xr = np.uint32(width - 1) - xv
        yr = np.uint32(height - 1) - yv
        on = np.uint32(1) if p[i] > 0 else np.uint32(0)
        if layout == 0:
            a = (yr << np.uint32(22)) | (xr << np.uint32(12)) | (on << np.uint32(11))
        else:
            a = (yr << np.uint32(8)) | (xr << np.uint32(1)) | (on ^ np.uint32(1))
        words[2 * i] = _bswap(a)
        words[2 * i + 1] = _bswap(np.uint32(t[i] & np.int64(0xFFFFFFFF)))
    return -1, gap
