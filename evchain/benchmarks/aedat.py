"""AEDAT 2.0 throughput: the ``aedat`` source and the ``aedat_writer`` sink, in events/s.

``limit_ratio`` = time of a plain numpy pass over the same bytes (``np.fromfile`` of the whole
file for reading, ``ndarray.tofile`` of the same bytes for writing) / time of the stage. Files
live in a temporary folder (normally the page cache, so this measures decoding, not the disk).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_time, cut_every, sink_row, source_row
from evchain.core.packets import EventPacket, Geometry
from evchain.io.aedat2 import AedatSource, AedatWriter, write_aedat2
from evchain.testing.synthetic import random_events

RATE_EPS = 1_000_000  # events per second of stream time: 10 ms packets of 10 000 events


def _data(n: int) -> str:
    return f"random events {n / 1e6:g} M, 240x180, 1 M events/s, 10 ms packets"


def _packets(n: int) -> list[EventPacket]:
    """``n`` random events on a DAVIS240, 10 ms packets of 10 000 events."""
    return cut_every(random_events(n, Geometry(240, 180), t_end=n * 1_000_000 // RATE_EPS))


def aedat_read(quick: bool) -> list[BenchRow]:
    n = 1_000_000 if quick else 10_000_000
    with tempfile.TemporaryDirectory() as tmp:
        path = write_aedat2(Path(tmp) / "bench.aedat", EventPacket.concat(_packets(n)))
        t_kernel = best_time(_decode_only(path), repeat=3)
        return [source_row("aedat-read", AedatSource, {"path": str(path)}, path, n,
                           {"packet_us": 10_000, "decode_kernel_eps": n / t_kernel},
                           _data(n))]


def _decode_only(path: Path):
    """The decoding kernel alone on the file's records in memory (no I/O, no packets)."""
    from evchain.io.aedat2 import read_header
    from evchain.kernels.aedat2 import decode

    h = read_header(path)
    words = np.fromfile(path, dtype="<u4", offset=h.data_offset)
    n = len(words) // 2
    out = (np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.int64),
           np.empty(n, np.int8))
    return lambda: decode(words, 0, 240, 180, 0, np.iinfo(np.int64).min, *out)


def aedat_write(quick: bool) -> list[BenchRow]:
    from evchain.kernels.aedat2 import encode

    n = 1_000_000 if quick else 10_000_000
    packets = _packets(n)
    ev = EventPacket.concat(packets)
    words = np.empty(2 * n, "<u4")
    t_kernel = best_time(lambda: encode(ev.x, ev.y, ev.t, ev.p, 0, 240, 180, 0, words), repeat=3)
    with tempfile.TemporaryDirectory() as tmp:
        return [sink_row("aedat-write", AedatWriter, packets, Path(tmp), "bench{}.aedat",
                         extra={"packet_us": 10_000, "encode_kernel_eps": n / t_kernel},
                         data=_data(n))]


WORKLOADS = {"aedat-read": aedat_read, "aedat-write": aedat_write}
