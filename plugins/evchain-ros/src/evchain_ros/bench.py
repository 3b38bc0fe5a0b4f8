"""ROS bag throughput (``evchain bench rosbag``): the ``rosbag`` source and ``rosbag_writer``
sink in events/s, ROS 1 .bag and ROS 2 (sqlite3) folder, 1 M events (``--quick``) or 5 M,
10 ms packets of 10 000 events (one EventArray message each); and ``imu-read-rosbag-ros1``:
the source on a ROS 1 bag of sensor_msgs/Imu messages at 1 kHz with one event each (in 10 ms
EventArray messages), 20 k samples (``--quick``) or 100 k, in IMU samples per CPU second of
reading the whole bag.

``limit_ratio`` = time of a plain numpy pass over the bag's bytes (``np.fromfile`` for
reading, ``ndarray.tofile`` for writing) / time of the stage; the files sit in the page cache.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from evchain.bench import BenchRow, cut_every, sink_row, source_row
from evchain.core.packets import EventPacket, Geometry
from evchain.testing.contract import run_sink
from evchain.testing.synthetic import random_events

T0 = 1_700_000_000_000_000  # a wall-clock epoch time in µs, as recorded bags have


def _data(n: int) -> str:
    return f"random events {n / 1e6:g} M, 346x260, 1 M events/s, 10 ms packets"


def bench_packets(n: int) -> list[EventPacket]:
    """``n`` random events on a DAVIS346 at 1 M events/s from ``T0``, in 10 ms packets."""
    return cut_every(random_events(n, Geometry(346, 260), t_start=T0, t_end=T0 + n), 10_000)


def write_bag(path: Path, packets: list[EventPacket], **params) -> Path:
    """Write ``packets`` with the ``rosbag_writer`` sink; returns ``path``."""
    from evchain_ros.rosbag import RosbagWriter

    run_sink(RosbagWriter, {"path": str(path), **params}, packets, path.parent)
    return path


def _name(fmt: str) -> str:
    return "b{}.bag" if fmt == "ros1" else "b{}"


def _read(fmt: str):
    def workload(quick: bool) -> list[BenchRow]:
        from evchain_ros.rosbag import RosbagSource

        n = 1_000_000 if quick else 5_000_000
        with tempfile.TemporaryDirectory() as tmp:
            path = write_bag(Path(tmp) / _name(fmt).format("ench"), bench_packets(n), format=fmt)
            return [source_row(f"rosbag-read-{fmt}", RosbagSource, {"path": str(path)}, path, n,
                               {"packet_us": 10_000}, _data(n))]
    return workload


def _write(fmt: str):
    def workload(quick: bool) -> list[BenchRow]:
        from evchain_ros.rosbag import RosbagWriter

        n = 1_000_000 if quick else 5_000_000
        with tempfile.TemporaryDirectory() as tmp:
            return [sink_row(f"rosbag-write-{fmt}", RosbagWriter, bench_packets(n), Path(tmp),
                             _name(fmt), {"format": fmt}, {"packet_us": 10_000}, _data(n))]
    return workload


def imu_read_rosbag(quick: bool) -> list[BenchRow]:
    from evchain.bench import imu_source_row
    from evchain.benchmarks.imu_truth import imu_data, imu_packets

    from evchain_ros.rosbag import RosbagSource

    n = 20_000 if quick else 100_000
    with tempfile.TemporaryDirectory() as tmp:
        path = write_bag(Path(tmp) / "imu.bag", imu_packets(n, Geometry(346, 260), t0=T0))
        return [imu_source_row("imu-read-rosbag-ros1", RosbagSource, {"path": str(path)}, path,
                               n, n, imu_data(n))]


WORKLOADS = {"rosbag-read-ros1": _read("ros1"), "rosbag-write-ros1": _write("ros1"),
             "rosbag-read-ros2": _read("ros2"), "rosbag-write-ros2": _write("ros2"),
             "imu-read-rosbag-ros1": imu_read_rosbag}
