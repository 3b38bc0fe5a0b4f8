"""Entry point of evchain-ros (group ``evchain``): the ROS bag source and sink, and their
benchmark workloads."""

from __future__ import annotations

from evchain import hookimpl


@hookimpl
def evchain_filters():
    from evchain_ros.rosbag import RosbagSource, RosbagWriter

    return [RosbagSource, RosbagWriter]


@hookimpl
def evchain_bench_workloads():
    from evchain_ros.bench import WORKLOADS

    return WORKLOADS
