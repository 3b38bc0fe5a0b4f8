"""Benchmarks of ``lk_flow``: rows ``flow-lk-<variant>-<workload>``.

Variants: the four gradients in calibrated mode (``backward``, ``central``, ``central2``,
``sg``) and jAER-faithful mode with the thesis's Savitzky-Golay gradient (``faithful-sg``) and
jAER's default central gradient (``faithful-central``). Parameters: the thesis's selection
(search distance 2, window 80 ms, refractory 150 ms, eigenvalue threshold 1.0).

* ``square``: the DVSFLOW16 translating square (``../shared/data/dvsflow16``; no rows when
  absent); error = AEE (px/s) against ``gtTranslatingSquare.mat`` (truth: 20 px/s).
* ``reference``: 10 s (2 s with ``--quick``) of the reference scene from the ``scene`` source
  and ``emulator`` when both are registered and run, else a synthetic expanding scene
  (:func:`evchain.benchmarks.flow_plane.expanding_scene_events`); ``extra["scene"]`` says which.
  Error = invalid rate (share of flow vectors more than 90° from p - FOE); AEE in ``extra``.

``throughput`` = input events / s of the filter's ``process`` over 10 ms packets (one thread,
Python per-packet overhead included, wall time); ``extra["kernel_ev_s"]`` = one ``process`` call
over the whole stream in CPU time. The machine is shared: numbers are noisy.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_time
from evchain.core.filter import Context
from evchain.core.packets import EventPacket
from evchain.testing.contract import recut

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dvsflow16"
THESIS = dict(search_distance=2, window_us=80_000, refractory_us=150_000, eig_threshold=1.0)
VARIANTS = {
    "backward": dict(mode="calibrated", gradient="backward"),
    "central": dict(mode="calibrated", gradient="central"),
    "central2": dict(mode="calibrated", gradient="central2"),
    "sg": dict(mode="calibrated", gradient="savitzky_golay"),
    "faithful-sg": dict(mode="faithful", gradient="savitzky_golay"),
    "faithful-central": dict(mode="faithful", gradient="central"),
}
_CACHE: dict[float, tuple] = {}


def _packets(ev: EventPacket, packet_us: int = 10_000) -> list[EventPacket]:
    return recut([ev], list(range(ev.t_start + packet_us, ev.t_end, packet_us)))


def _run(packets, params):
    from evchain.filters.lk_flow import LKFlow

    f = LKFlow()
    f.setup(LKFlow.Params(**params), Context(geometry=packets[0].geometry))
    outs = [f.process(p) for p in packets]
    last = f.flush()
    if last is not None:
        outs.append(last)
    return outs


def _kernel_rate(ev: EventPacket, params, repeat: int) -> float:
    """Input events per CPU second of one ``process`` call over the whole stream (state reset
    outside the timed part). CPU time, because the machine is shared."""
    from evchain.filters.lk_flow import LKFlow

    f = LKFlow()
    f.setup(LKFlow.Params(**params), Context(geometry=ev.geometry))
    f.process(ev)  # compile / warm up
    best = float("inf")
    for _ in range(max(repeat, 1)):
        f.reset()
        c0 = time.process_time()
        f.process(ev)
        best = min(best, time.process_time() - c0)
    return len(ev) / max(best, 1e-9)


def _rows(workload, ev, truth, error_key, quick, extra) -> list[BenchRow]:
    from evchain.filters.flow_scorer import score_flow

    packets = _packets(ev)
    n_in = len(ev)
    rows = []
    for variant, vparams in VARIANTS.items():
        prm = {**THESIS, **vparams}
        outs = _run(packets, prm)
        secs = best_time(lambda prm=prm: _run(packets, prm), repeat=1 if quick else 3)
        x, y, t, vx, vy = (np.concatenate([getattr(o, c) for o in outs])
                           for c in ("x", "y", "t", "vx", "vy"))
        m = score_flow(x, y, t, vx, vy, truth)
        rows.append(BenchRow(
            workload=f"flow-lk-{variant}-{workload}", stage="lk_flow", throughput=n_in / secs,
            unit="ev/s", error=m[error_key], error_name=error_key,
            extra={**extra, "events_in": n_in, "flow_events": int(len(x)),
                   "density": len(x) / n_in if n_in else None,
                   "kernel_ev_s": _kernel_rate(ev, prm, 1 if quick else 3),
                   "aee_pxs": m["aee_pxs"], "aee_normal_pxs": m["aee_normal_pxs"],
                   "aae_deg": m["aae_deg"], "invalid_rate": m["invalid_rate"],
                   "ree_pct": m["ree_pct"], "n_scored": m["n_scored"], "params": prm}))
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
    return _rows("square", ev, truth, "aee_pxs", quick, {"data": "DVSFLOW16 TranslatingSquare"})


def reference_stream(seconds: float):
    """(events, truth, label): the first ``seconds`` of the simulator's reference scene (scene
    + emulator, defaults) when available, else the synthetic expanding scene. Cached per
    process."""
    if seconds in _CACHE:
        return _CACHE[seconds]
    from evchain.benchmarks.flow_plane import expanding_scene_events

    label = "synthetic expanding scene (scene/emulator not available)"
    result = None
    try:
        from evchain.core.chain import Chain
        from evchain.core.config import pipeline_from_text
        from evchain.core.registry import make_registry

        reg = make_registry()
        if "scene" in reg.filters and "emulator" in reg.filters:
            spec = pipeline_from_text("chain:\n  - use: scene\n  - use: emulator\n",
                                      "<flow-lk-bench>", reg)
            ctx = Context(seed=0)
            chain = Chain(spec, ctx)
            chain.setup()
            parts = []
            t0 = time.perf_counter()
            try:
                for packet in chain.stream():
                    if len(packet):
                        parts.append(packet)
                    if packet.t_end >= seconds * 1e6:
                        break
            finally:
                chain.close()
            if parts and ctx.truth is not None and hasattr(ctx.truth, "foe"):
                ev = EventPacket.concat(parts)
                keep = ev.t < int(seconds * 1e6)
                ev = ev.select(keep).replace(t_end=int(seconds * 1e6))
                result = (ev, ctx.truth, f"scene+emulator (defaults), simulated in "
                                         f"{time.perf_counter() - t0:.0f} s")
    except Exception as exc:  # the simulator is optional here: fall back and say so
        label = f"synthetic expanding scene (scene/emulator failed: {type(exc).__name__})"
    if result is None:
        ev, truth = expanding_scene_events(seconds)
        result = (ev, truth, label)
    _CACHE[seconds] = result
    return result


def bench_reference(quick: bool) -> list[BenchRow]:
    seconds = 2.0 if quick else 10.0
    ev, truth, label = reference_stream(seconds)
    return _rows("reference", ev, truth, "invalid_rate", quick,
                 {"scene": label, "seconds": seconds})


WORKLOADS = {"flow-lk-square": bench_square, "flow-lk-reference": bench_reference}
