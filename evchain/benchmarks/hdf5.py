"""HDF5 throughput (needs ``evchain[hdf5]``): the ``hdf5`` source and the ``hdf5_writer`` sink,
in events/s, uncompressed, with gzip and with Blosc (zstd, as DSEC's files), 1 M events
(``--quick``) or 5 M on a DAVIS346, 10 ms packets.

``limit_ratio`` = time of a plain numpy pass over the file's bytes / time of the stage. The
rows are left out when h5py (for Blosc: hdf5plugin) is not installed.
"""

from __future__ import annotations

import importlib.util
import tempfile
from pathlib import Path

from evchain.bench import BenchRow, cut_every, sink_row, source_row
from evchain.core.packets import EventPacket, Geometry
from evchain.io.hdf5 import Hdf5Source, Hdf5Writer
from evchain.testing.contract import run_sink
from evchain.testing.synthetic import random_events


def _packets(n: int) -> list[EventPacket]:
    return cut_every(random_events(n, Geometry(346, 260), t_end=n), 10_000)


SUFFIX = {"none": "", "gzip": "-gzip", "blosc": "-blosc"}


def _workload(read: bool, compression: str):
    def workload(quick: bool) -> list[BenchRow]:
        if importlib.util.find_spec("h5py") is None or (
                compression == "blosc" and importlib.util.find_spec("hdf5plugin") is None):
            return []
        n = 1_000_000 if quick else 5_000_000
        name = f"hdf5-{'read' if read else 'write'}{SUFFIX[compression]}"
        extra = {"packet_us": 10_000, "compression": compression}
        data = f"random events {n / 1e6:g} M, 346x260, 1 M events/s, 10 ms packets"
        with tempfile.TemporaryDirectory() as tmp:
            if not read:
                return [sink_row(name, Hdf5Writer, _packets(n), Path(tmp), "b{}.h5",
                                 {"compression": compression}, extra, data)]
            path = Path(tmp) / "bench.h5"
            run_sink(Hdf5Writer, {"path": str(path), "compression": compression}, _packets(n),
                     Path(tmp))
            return [source_row(name, Hdf5Source, {"path": str(path)}, path, n, extra, data)]
    return workload


WORKLOADS = {f"hdf5-{op}{suffix}": _workload(op == "read", compression)
             for op in ("read", "write") for compression, suffix in SUFFIX.items()}
