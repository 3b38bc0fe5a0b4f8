"""Entry point of evchain-dv (group ``evchain``): the AEDAT 4.0 file source and sink, the live
network source and server, and their benchmark workloads."""

from __future__ import annotations

from evchain import hookimpl


@hookimpl
def evchain_filters():
    from evchain_dv.aedat4 import Aedat4Source, Aedat4Writer
    from evchain_dv.network import DvNetworkServer, DvNetworkSource

    return [Aedat4Source, Aedat4Writer, DvNetworkSource, DvNetworkServer]


@hookimpl
def evchain_bench_workloads():
    from evchain_dv import bench, bench_network

    return {**bench.WORKLOADS, **bench_network.WORKLOADS}
