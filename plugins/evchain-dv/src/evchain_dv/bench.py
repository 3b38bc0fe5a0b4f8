"""AEDAT 4.0 throughput (``evchain bench aedat4``): the ``aedat4`` source and ``aedat4_writer``
sink in events/s, 1 M events (``--quick``) or 5 M, 10 ms packets of 10 000 events; and
``imu-read-aedat4``: the source on a file of IMU samples at 1 kHz with one event each, 50 k
samples (``--quick``) or 200 k, in IMU samples per CPU second of reading the whole file.

``limit_ratio`` = time of a plain numpy pass over the file's bytes (``np.fromfile`` for reading,
``ndarray.tofile`` for writing) / time of the stage; the file sits in the page cache.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from evchain.bench import BenchRow, cut_every, sink_row, source_row
from evchain.core.packets import EventPacket, Geometry
from evchain.testing.contract import run_sink
from evchain.testing.synthetic import random_events


def _data(n: int) -> str:
    return f"random events {n / 1e6:g} M, 346x260, 1 M events/s, 10 ms packets"


def bench_packets(n: int) -> list[EventPacket]:
    """``n`` random events on a DAVIS346 at 1 M events/s, in 10 ms packets."""
    return cut_every(random_events(n, Geometry(346, 260), t_end=n), 10_000)


def write_file(path: Path, packets: list[EventPacket], **params) -> Path:
    """Write ``packets`` with the ``aedat4_writer`` sink; returns ``path``."""
    from evchain_dv.aedat4 import Aedat4Writer

    run_sink(Aedat4Writer, {"path": str(path), **params}, packets, path.parent)
    return path


def aedat4_read(quick: bool) -> list[BenchRow]:
    from evchain_dv.aedat4 import Aedat4Source

    n = 1_000_000 if quick else 5_000_000
    with tempfile.TemporaryDirectory() as tmp:
        path = write_file(Path(tmp) / "bench.aedat4", bench_packets(n))
        return [source_row("aedat4-read", Aedat4Source, {"path": str(path)}, path, n,
                           {"packet_us": 10_000}, _data(n))]


def aedat4_write(quick: bool) -> list[BenchRow]:
    from evchain_dv.aedat4 import Aedat4Writer

    n = 1_000_000 if quick else 5_000_000
    with tempfile.TemporaryDirectory() as tmp:
        return [sink_row("aedat4-write", Aedat4Writer, bench_packets(n), Path(tmp),
                         "b{}.aedat4", extra={"packet_us": 10_000}, data=_data(n))]


def imu_read_aedat4(quick: bool) -> list[BenchRow]:
    from evchain.bench import imu_source_row
    from evchain.benchmarks.imu_truth import imu_data, imu_packets

    from evchain_dv.aedat4 import Aedat4Source

    n = 50_000 if quick else 200_000
    with tempfile.TemporaryDirectory() as tmp:
        path = write_file(Path(tmp) / "imu.aedat4", imu_packets(n, Geometry(346, 260)))
        return [imu_source_row("imu-read-aedat4", Aedat4Source, {"path": str(path)}, path, n,
                               n, imu_data(n))]


WORKLOADS = {"aedat4-read": aedat4_read, "aedat4-write": aedat4_write,
             "imu-read-aedat4": imu_read_aedat4}
