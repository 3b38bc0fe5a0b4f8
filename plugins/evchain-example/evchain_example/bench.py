"""Benchmark workload of the plugin (``evchain bench background-activity``)."""

from __future__ import annotations

from evchain.bench import BenchRow, best_time
from evchain.core.filter import Context
from evchain.core.packets import Geometry
from evchain.testing.synthetic import random_events
from evchain_example.background_activity import BackgroundActivityFilter


def background_activity(quick: bool) -> list[BenchRow]:
    n = 200_000 if quick else 2_000_000
    g = Geometry(240, 180)
    ev = random_events(n, g, 0, n, seed=0)  # 1 event per µs over the sensor
    f = BackgroundActivityFilter()
    f.setup(BackgroundActivityFilter.Params(), Context(geometry=g))

    def run():
        f.reset()
        return f.process(ev)

    seconds = best_time(run, repeat=3)
    kept = len(run()) / n
    return [BenchRow("background-activity", "background_activity", n / seconds, "events/s",
                     None, None, None, {"events": n, "kept_fraction": kept},
                     data=f"random events {n / 1e6:g} M, 240x180, 1 event/µs")]
