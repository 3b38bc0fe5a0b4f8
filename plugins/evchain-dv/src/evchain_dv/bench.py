"""AEDAT 4.0 throughput (``evchain bench aedat4``): the ``aedat4`` source and ``aedat4_writer``
sink in events/s, 1 M events (``--quick``) or 5 M, 10 ms packets of 10 000 events.

``limit_ratio`` = time of a plain numpy pass over the file's bytes (``np.fromfile`` for reading,
``ndarray.tofile`` for writing) / time of the stage; the file sits in the page cache.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from evchain.bench import BenchRow, best_time
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry


def bench_events(n: int, geometry: Geometry = Geometry(346, 260)) -> EventPacket:
    """``n`` random events at 1 M events/s (stream time), sorted by time."""
    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(0, n, n)).astype(np.int64)
    return EventPacket(geometry=geometry, t_start=0, t_end=int(t[-1]) + 1,
                       x=rng.integers(0, geometry.width, n).astype(np.uint16),
                       y=rng.integers(0, geometry.height, n).astype(np.uint16),
                       t=t, p=rng.choice(np.array([-1, 1], np.int8), n))


def split(ev: EventPacket, packet_us: int) -> list[EventPacket]:
    """``ev`` cut into consecutive slices of ``packet_us``."""
    edges = np.append(np.arange(ev.t_start, ev.t_end, packet_us), ev.t_end)
    idx = np.searchsorted(ev.t, edges)
    return [ev.replace(t_start=int(a), t_end=int(b), **{c: getattr(ev, c)[i:j]
                                                        for c in EventPacket.columns})
            for a, b, i, j in zip(edges[:-1], edges[1:], idx[:-1], idx[1:], strict=True)]


def write_file(path: Path, packets: list[EventPacket], **params) -> Path:
    from evchain_dv.aedat4 import Aedat4Writer

    w = Aedat4Writer()
    w.id = "aedat4_writer"
    w.setup(Aedat4Writer.Params(path=str(path), **params),
            Context(out_dir=path.parent, geometry=packets[0].geometry))
    try:
        for p in packets:
            w.process(p)
        w.flush()
    finally:
        w.close()
    return path


def aedat4_read(quick: bool) -> list[BenchRow]:
    from evchain_dv.aedat4 import Aedat4Source

    n = 1_000_000 if quick else 5_000_000
    with tempfile.TemporaryDirectory() as tmp:
        path = write_file(Path(tmp) / "bench.aedat4", split(bench_events(n), 10_000))

        def stage():
            src = Aedat4Source()
            src.id = "aedat4"
            src.setup(Aedat4Source.Params(path=str(path)), Context(out_dir=Path(tmp)))
            count = sum(len(p) for p in src.packets())
            src.close()
            if count != n:
                raise RuntimeError(f"read {count} events, wrote {n}")

        t_stage = best_time(stage, repeat=3)
        t_limit = best_time(lambda: np.fromfile(path, dtype=np.uint8), repeat=3)
        size = path.stat().st_size
    return [BenchRow("aedat4-read", "aedat4", n / t_stage, "events/s", None, None,
                     t_limit / t_stage, {"events": n, "packet_us": 10_000, "bytes": size})]


def aedat4_write(quick: bool) -> list[BenchRow]:
    n = 1_000_000 if quick else 5_000_000
    packets = split(bench_events(n), 10_000)
    with tempfile.TemporaryDirectory() as tmp:
        runs = iter(range(100))
        t_stage = best_time(lambda: write_file(Path(tmp) / f"b{next(runs)}.aedat4", packets),
                            repeat=2)
        data = np.fromfile(Path(tmp) / "b0.aedat4", dtype=np.uint8)
        t_limit = best_time(lambda: data.tofile(Path(tmp) / f"plain{next(runs)}.bin"), repeat=3)
    return [BenchRow("aedat4-write", "aedat4_writer", n / t_stage, "events/s", None, None,
                     t_limit / t_stage, {"events": n, "packet_us": 10_000})]


WORKLOADS = {"aedat4-read": aedat4_read, "aedat4-write": aedat4_write}
