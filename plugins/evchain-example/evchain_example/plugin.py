"""The module the ``evchain`` entry point names: hook implementations only, nothing per event."""

from __future__ import annotations

import evchain.hookspecs
from evchain_example.background_activity import BackgroundActivityFilter


@evchain.hookspecs.hookimpl
def evchain_filters():
    """The filters this plugin adds (their ``name`` is the ``use:`` key in pipelines)."""
    return [BackgroundActivityFilter]


@evchain.hookspecs.hookimpl
def evchain_bench_workloads():
    """``evchain bench background-activity`` rows."""
    from evchain_example.bench import background_activity

    return {"background-activity": background_activity}
