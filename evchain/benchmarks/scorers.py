"""Scorer throughput: ``flow_scorer`` in flow events/s, scoring a pure expansion whose flow
carries Gaussian noise of a known size, so the AEE it must report is known analytically.

Noise of ``NOISE_FRAC`` x the local speed on each component has a Rayleigh-distributed length
with mean ``NOISE_FRAC * speed * sqrt(pi / 2)``; the row's error is the relative deviation of the
scorer's AEE from that expectation (sampling noise, about 1/sqrt(events)).
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_cpu_time, best_time
from evchain.core.packets import FlowPacket
from evchain.testing.contract import make_context, run_filter
from evchain.testing.synthetic import ExpansionTruth, approach_flow_packets

FOE = (60.0, 45.0)
TAU_S = 20.0  # time to collision at t = 0; the stream ends before it (at most 10 s)
NOISE_FRAC = 0.1


def flow_scorer(quick: bool) -> list[BenchRow]:
    from evchain.filters.flow_scorer import FlowScorer

    n = 200_000 if quick else 2_000_000
    duration_us = n * 5  # 200 k flow events/s of stream time, 20 ms packets
    packets = approach_flow_packets(FOE, TAU_S, n, duration_us=duration_us,
                                    n_packets=duration_us // 20_000, noise_frac=NOISE_FRAC,
                                    tau_shrinks=True)
    truth = ExpansionTruth(FOE, t_collision_s=TAU_S)
    flow = FlowPacket.concat(packets)
    speed = np.hypot(flow.x - FOE[0], flow.y - FOE[1]) / truth.ttc(flow.t)
    expected_aee = NOISE_FRAC * math.sqrt(math.pi / 2) * float(speed.mean())
    with tempfile.TemporaryDirectory() as tmp:
        context = make_context(packets[0].geometry, truth, Path(tmp))
        got = {}

        def stage():
            f = FlowScorer()
            f.id = "flow_scorer"
            f.setup(FlowScorer.Params(), context)
            run_filter(f, packets, check=False)
            got.update(context.metrics["flow"])

        t_stage = best_time(stage)
        cpu = best_cpu_time(stage)
    error = abs(got["aee_pxs"] / expected_aee - 1)
    return [BenchRow("scorer-flow", "flow_scorer", n / t_stage, "events/s", error,
                     "rel. deviation of AEE", None,
                     {"events": n, "aee_pxs": got["aee_pxs"], "expected_aee_pxs": expected_aee,
                      "cpu_time_eps": n / cpu},
                     data=f"synthetic expansion flow {n / 1e6:g} M events, "
                          f"{NOISE_FRAC * 100:g} % Gaussian noise")]


WORKLOADS = {"scorer-flow": flow_scorer}
