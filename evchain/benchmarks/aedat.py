"""AEDAT 2.0 throughput: the ``aedat`` source and the ``aedat_writer`` sink, in events/s.

``limit_ratio`` = time of a plain numpy pass over the same bytes (``np.fromfile`` of the whole
file for reading, ``ndarray.tofile`` of the same bytes for writing) / time of the stage. Files
live in a temporary folder (normally the page cache, so this measures decoding, not the disk).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_cpu_time, best_time
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.io.aedat2 import AedatSource, AedatWriter, write_aedat2

RATE_EPS = 1_000_000  # events per second of stream time: 10 ms packets of 10 000 events


def _events(n: int) -> EventPacket:
    rng = np.random.default_rng(0)
    g = Geometry(240, 180)
    t = np.sort(rng.integers(0, n * 1_000_000 // RATE_EPS, n)).astype(np.int64)
    return EventPacket(geometry=g, t_start=0, t_end=int(t[-1]) + 1,
                       x=rng.integers(0, g.width, n).astype(np.uint16),
                       y=rng.integers(0, g.height, n).astype(np.uint16),
                       t=t, p=rng.choice(np.array([-1, 1], np.int8), n))


def _split(ev: EventPacket, packet_us: int) -> list[EventPacket]:
    edges = np.arange(ev.t_start, ev.t_end + packet_us, packet_us)
    idx = np.searchsorted(ev.t, edges)
    return [ev.replace(t_start=int(a), t_end=int(b), **{c: getattr(ev, c)[i:j]
                                                        for c in EventPacket.columns})
            for a, b, i, j in zip(edges[:-1], edges[1:], idx[:-1], idx[1:], strict=True)]


def aedat_read(quick: bool) -> list[BenchRow]:
    n = 1_000_000 if quick else 10_000_000
    with tempfile.TemporaryDirectory() as tmp:
        path = write_aedat2(Path(tmp) / "bench.aedat", _events(n))

        def stage():
            src = AedatSource()
            src.id = "aedat"
            src.setup(AedatSource.Params(path=str(path)), Context(out_dir=Path(tmp)))
            count = sum(len(p) for p in src.packets())
            src.close()
            assert count == n

        t_stage = best_time(stage, repeat=3)
        t_limit = best_time(lambda: np.fromfile(path, dtype=np.uint8), repeat=3)
        t_kernel = best_time(_decode_only(path), repeat=3)
        cpu = best_cpu_time(stage)
    return [BenchRow("aedat-read", "aedat", n / t_stage, "events/s", None, None,
                     t_limit / t_stage, {"events": n, "packet_us": 10_000,
                                         "decode_kernel_eps": n / t_kernel,
                                         "cpu_time_eps": n / cpu})]


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
    packets = _split(_events(n), 10_000)
    with tempfile.TemporaryDirectory() as tmp:
        ctx = Context(out_dir=Path(tmp), geometry=packets[0].geometry)
        runs = iter(range(1000))

        def stage():  # a new name each time: replacing a big file costs more than writing it
            w = AedatWriter()
            w.id = "aedat_writer"
            w.setup(AedatWriter.Params(path=f"bench{next(runs)}.aedat"), ctx)
            for p in packets:
                w.process(p)
            w.flush()
            w.close()

        t_stage = best_time(stage, repeat=3)
        cpu = best_cpu_time(stage)
        data = np.fromfile(Path(tmp) / "bench0.aedat", dtype=np.uint8)
        t_limit = best_time(lambda: data.tofile(Path(tmp) / f"plain{next(runs)}.bin"), repeat=3)
    ev = EventPacket.concat(packets)
    words = np.empty(2 * n, "<u4")
    t_kernel = best_time(lambda: encode(ev.x, ev.y, ev.t, ev.p, 0, 240, 180, 0, words), repeat=3)
    return [BenchRow("aedat-write", "aedat_writer", n / t_stage, "events/s", None, None,
                     t_limit / t_stage, {"events": n, "packet_us": 10_000,
                                         "encode_kernel_eps": n / t_kernel,
                                         "cpu_time_eps": n / cpu})]


WORKLOADS = {"aedat-read": aedat_read, "aedat-write": aedat_write}
