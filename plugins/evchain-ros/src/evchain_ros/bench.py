"""ROS bag throughput (``evchain bench rosbag``): the ``rosbag`` source and ``rosbag_writer``
sink in events/s, ROS 1 .bag and ROS 2 (sqlite3) folder, 1 M events (``--quick``) or 5 M,
10 ms packets of 10 000 events (one EventArray message each).

``limit_ratio`` = time of a plain numpy pass over the bag's bytes (``np.fromfile`` for
reading, ``ndarray.tofile`` for writing) / time of the stage; the files sit in the page cache.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from evchain.bench import BenchRow, best_time
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry


def bench_events(n: int, geometry: Geometry = Geometry(346, 260),
                 t_start: int = 1_700_000_000_000_000) -> EventPacket:
    """``n`` random events at 1 M events/s (stream time) from ``t_start``, sorted by time."""
    rng = np.random.default_rng(0)
    t = t_start + np.sort(rng.integers(0, n, n)).astype(np.int64)
    return EventPacket(geometry=geometry, t_start=t_start, t_end=int(t[-1]) + 1,
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


def write_bag(path: Path, packets: list[EventPacket], **params) -> Path:
    """Write ``packets`` with the ``rosbag_writer`` sink; returns ``path``."""
    from evchain_ros.rosbag import RosbagWriter

    w = RosbagWriter()
    w.id = "rosbag_writer"
    w.setup(RosbagWriter.Params(path=str(path), **params),
            Context(out_dir=path.parent, geometry=packets[0].geometry))
    try:
        for p in packets:
            w.process(p)
        w.flush()
    finally:
        w.close()
    return path


def _bytes(path: Path) -> list[Path]:
    return sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]


def _read(fmt: str):
    def workload(quick: bool) -> list[BenchRow]:
        from evchain_ros.rosbag import RosbagSource

        n = 1_000_000 if quick else 5_000_000
        with tempfile.TemporaryDirectory() as tmp:
            path = write_bag(Path(tmp) / ("bench.bag" if fmt == "ros1" else "bench"),
                             split(bench_events(n), 10_000), format=fmt)

            def stage():
                src = RosbagSource()
                src.id = "rosbag"
                src.setup(RosbagSource.Params(path=str(path)), Context(out_dir=Path(tmp)))
                count = sum(len(p) for p in src.packets())
                src.close()
                if count != n:
                    raise RuntimeError(f"read {count} events, wrote {n}")

            t_stage = best_time(stage, repeat=3)
            files = _bytes(path)
            t_limit = best_time(lambda: [np.fromfile(f, np.uint8) for f in files], repeat=3)
            size = sum(f.stat().st_size for f in files)
        return [BenchRow(f"rosbag-read-{fmt}", "rosbag", n / t_stage, "events/s", None, None,
                         t_limit / t_stage, {"events": n, "packet_us": 10_000, "bytes": size})]
    return workload


def _write(fmt: str):
    def workload(quick: bool) -> list[BenchRow]:
        n = 1_000_000 if quick else 5_000_000
        packets = split(bench_events(n), 10_000)
        with tempfile.TemporaryDirectory() as tmp:
            runs = iter(range(100))
            name = "b{}.bag" if fmt == "ros1" else "b{}"
            t_stage = best_time(lambda: write_bag(Path(tmp) / name.format(next(runs)), packets,
                                                  format=fmt), repeat=2)
            data = np.concatenate([np.fromfile(f, np.uint8)
                                   for f in _bytes(Path(tmp) / name.format(0))])
            t_limit = best_time(lambda: data.tofile(Path(tmp) / f"plain{next(runs)}.bin"),
                                repeat=3)
        return [BenchRow(f"rosbag-write-{fmt}", "rosbag_writer", n / t_stage, "events/s", None,
                         None, t_limit / t_stage, {"events": n, "packet_us": 10_000})]
    return workload


WORKLOADS = {"rosbag-read-ros1": _read("ros1"), "rosbag-write-ros1": _write("ros1"),
             "rosbag-read-ros2": _read("ros2"), "rosbag-write-ros2": _write("ros2")}
