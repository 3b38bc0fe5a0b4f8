"""``refractory`` and ``polarity`` throughput, in events/s.

``limit_ratio`` = time of selecting the same events with their precomputed mask (one numpy
boolean-index pass over the columns, which every filter that drops events pays) / time of the
stage.
"""

from __future__ import annotations

import numpy as np

from evchain.bench import BenchRow, best_time
from evchain.core.filter import Context
from evchain.core.packets import Geometry
from evchain.filters.polarity import Polarity
from evchain.filters.refractory import Refractory
from evchain.testing.synthetic import random_events


def _refractory_mask(ev, period_us: int) -> np.ndarray:
    from evchain.filters.refractory import NEVER
    from evchain.kernels.refractory import refractory

    last = np.full((1, *ev.geometry.shape), NEVER, np.int64)
    keep = np.empty(len(ev), np.bool_)
    refractory(ev.x, ev.y, ev.t, ev.p, last, period_us, False, keep)
    return keep


def _run(cls, params, quick: bool, workload: str, mask_of) -> list[BenchRow]:
    n = 1_000_000 if quick else 5_000_000
    g = Geometry(240, 180)
    ev = random_events(n, g, 0, n // 10, seed=0)  # 10 events/µs: many refractory hits
    f = cls()
    f.setup(cls.Params(**params), Context(geometry=g))

    def stage():
        f.reset()
        return f.process(ev)

    t_stage = best_time(stage, repeat=3)
    out = stage()
    keep = mask_of(ev)
    if not np.array_equal(ev.t[keep], out.t):
        raise RuntimeError(f"{workload}: the limit's mask does not select the stage's output")
    t_limit = best_time(lambda: ev.select(keep), repeat=3)
    return [BenchRow(workload, cls.name, n / t_stage, "events/s", None, None, t_limit / t_stage,
                     {"events": n, "kept_fraction": len(out) / n},
                     data=f"random events {n / 1e6:g} M, 240x180, 10 events/µs")]


WORKLOADS = {
    "refractory": lambda quick: _run(Refractory, {"period_us": 1000}, quick, "refractory",
                                     lambda ev: _refractory_mask(ev, 1000)),
    "polarity": lambda quick: _run(Polarity, {"keep": "on"}, quick, "polarity",
                                   lambda ev: ev.p > 0),
}
