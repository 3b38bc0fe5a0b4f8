"""Entry point of evchain-dv (group ``evchain``): the AEDAT 4.0 source and sink, and their
benchmark workloads."""

from __future__ import annotations

from evchain import hookimpl


@hookimpl
def evchain_filters():
    from evchain_dv.aedat4 import Aedat4Source, Aedat4Writer

    return [Aedat4Source, Aedat4Writer]


@hookimpl
def evchain_bench_workloads():
    from evchain_dv.bench import WORKLOADS

    return WORKLOADS
