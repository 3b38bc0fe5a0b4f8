"""Benchmarks of ``lk_flow``: rows ``flow-lk-<variant>-<workload>``.

Variants: the four gradients in calibrated mode (``backward``, ``central``, ``central2``,
``sg``) and jAER-faithful mode with the thesis's Savitzky-Golay gradient (``faithful-sg``) and
jAER's default central gradient (``faithful-central``). Parameters: the thesis's selection
(search distance 2, window 80 ms, refractory 150 ms, eigenvalue threshold 1.0).

* ``square`` (workload ``flow-lk-square``): the DVSFLOW16 translating square
  (``../shared/data/dvsflow16``; no rows when absent); error = AEE (px/s) against
  ``gtTranslatingSquare.mat`` (truth: 20 px/s).
* ``reference`` (``flow-lk-reference``): the first 10 s (2 s with ``--quick``) of the reference
  drive as pipelines/reference.yaml renders it, a cached input shared with the plane-fit
  benchmark (:func:`evchain.benchmarks.plane_flow.reference_input`; ``evchain bench --prepare
  flow-lk-reference`` makes it); exact ground truth from the scene. Error = invalid rate (share
  of flow vectors more than 90° from p - FOE); AEE in ``extra``.
* ``expanding`` (``flow-lk-expanding``): the synthetic expanding scene of
  :func:`evchain.benchmarks.plane_flow.expanding_scene_events` (240x180, 10 s, 2 s with
  ``--quick``), error as for ``reference``.

``throughput`` = input events / s of the filter's ``process`` over 10 ms packets (one thread,
Python per-packet overhead included), from the thread's CPU time because the machine is shared
(``extra["throughput_wall_eps"]`` has wall time); ``extra["kernel_ev_s"]`` = one ``process``
call over the whole stream in CPU time. Numbers are noisy.
"""

from __future__ import annotations

import time
from pathlib import Path

from evchain.bench import BenchRow, cut_every
from evchain.bench_cache import Workload
from evchain.benchmarks.plane_flow import (
    expanding_data,
    expanding_scene_events,
    expanding_seconds,
    flow_row,
    reference_input,
    reference_stream,
)
from evchain.core.filter import Context
from evchain.core.packets import EventPacket
from evchain.testing.contract import run_filter

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dvsflow16"
#: the thesis's selection, a fixed window, whatever the camera (the filter's defaults adapt the
#: window to slow edges and derive the windows and the speed ceiling from the focal length)
THESIS = dict(search_distance=2, window_us=80_000, refractory_us=150_000, eig_threshold=1.0,
              max_window_us=0, max_speed_pxs=1e5)
VARIANTS = {
    "backward": dict(mode="calibrated", gradient="backward"),
    "central": dict(mode="calibrated", gradient="central"),
    "central2": dict(mode="calibrated", gradient="central2"),
    "sg": dict(mode="calibrated", gradient="savitzky_golay"),
    "faithful-sg": dict(mode="faithful", gradient="savitzky_golay"),
    "faithful-central": dict(mode="faithful", gradient="central"),
}


def _lk(params, packets):
    """One pass of ``LKFlow`` with ``params`` over ``packets`` (process, then flush)."""
    from evchain.filters.lk_flow import LKFlow

    f = LKFlow()
    f.setup(LKFlow.Params(**params), Context(geometry=packets[0].geometry))
    return run_filter(f, packets, check=False)


def _kernel_rate(ev: EventPacket, params, repeat: int) -> float:
    """Input events per CPU second (the thread's) of one ``process`` call over the whole stream
    (state reset outside the timed part). CPU time, because the machine is shared."""
    from evchain.filters.lk_flow import LKFlow

    f = LKFlow()
    f.setup(LKFlow.Params(**params), Context(geometry=ev.geometry))
    f.process(ev)  # compile / warm up
    best = float("inf")
    for _ in range(max(repeat, 1)):
        f.reset()
        c0 = time.thread_time()
        f.process(ev)
        best = min(best, time.thread_time() - c0)
    return len(ev) / max(best, 1e-9)


def _rows(workload, ev, truth, error_key, quick, data) -> list[BenchRow]:
    packets = cut_every(ev)
    rows = []
    for variant, vparams in VARIANTS.items():
        prm = {**THESIS, **vparams}
        rows.append(flow_row(f"flow-lk-{variant}-{workload}", "lk_flow",
                             lambda prm=prm: _lk(prm, packets), packets, truth, error_key, quick,
                             {"params": prm,
                              "kernel_ev_s": _kernel_rate(ev, prm, 1 if quick else 3)}, data))
    return rows


def bench_square(quick: bool) -> list[BenchRow]:
    path = DATA / "TranslatingSquare.aedat"
    gt = DATA / "gtTranslatingSquare.mat"
    if not (path.is_file() and gt.is_file()):
        return []
    from evchain.io.aedat2 import read_aedat2
    from evchain.io.dvsflow16 import DVSFLOW16Truth

    ev = read_aedat2(path, chip="davis240")
    truth = DVSFLOW16Truth(gt, 180, 240)
    return _rows("square", ev, truth, "aee_pxs", quick,
                 "DVSFLOW16 TranslatingSquare, thesis parameters")


def bench_reference(quick: bool) -> list[BenchRow]:
    ev, truth, data = reference_stream(quick)
    return _rows("reference", ev, truth, "invalid_rate", quick, f"{data}, thesis parameters")


def bench_expanding(quick: bool) -> list[BenchRow]:
    ev, truth = expanding_scene_events(expanding_seconds(quick))
    return _rows("expanding", ev, truth, "invalid_rate", quick,
                 f"{expanding_data(quick)}, thesis parameters")


WORKLOADS = {"flow-lk-square": bench_square,
             "flow-lk-reference": Workload(bench_reference, lambda q: [reference_input(q)]),
             "flow-lk-expanding": bench_expanding}
