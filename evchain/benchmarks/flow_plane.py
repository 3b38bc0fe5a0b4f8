"""Benchmarks of ``plane_flow``: rows ``flow-plane-<variant>-<workload>``.

* ``square``: the DVSFLOW16 translating square (``../shared/data/dvsflow16``; skipped when
  absent); error = AEE (px/s) against the file's ground truth, window 100 ms, no refractory.
* ``reference``: 10 s of the reference scene with the thesis's selected parameters (search
  distance 2, window 80 ms, refractory 150 ms); error = invalid rate (0-1) against the
  ground-truth FOE, AEE in ``extra``. Uses the ``scene`` source and the ``emulator`` when both are
  registered, else :func:`expanding_scene_events` (a synthetic expanding scene; the row's
  ``extra["scene"]`` says which).

Throughput = input events / s of the filter's ``process`` over 10 ms packets, one thread.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_time
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.filters.flow_scorer import score_flow
from evchain.filters.plane_flow import PlaneFlow
from evchain.testing.contract import recut
from evchain.testing.synthetic import ExpansionTruth

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dvsflow16"
VARIANTS = ("single", "iterative", "robust", "original", "savitzky_golay")
SHORT = {"single": "single", "iterative": "iterative", "robust": "robust",
         "original": "original", "savitzky_golay": "sg"}
REFERENCE_PARAMS = dict(search_distance=2, window_us=80_000, refractory_us=150_000)


def expanding_scene_events(seconds: float = 10.0, geometry: Geometry = Geometry(240, 180),
                           foe: tuple[float, float] = (131.0, 82.0), t_collision_s: float = 12.0,
                           n_segments: int = 3000, seed: int = 0
                           ) -> tuple[EventPacket, ExpansionTruth]:
    """Events of a camera approaching a fronto-parallel plane covered with straight segments.

    The image scales about the FOE by s(t) = tau0 / (tau0 - t); a pixel p fires (once per
    segment, with the segment's polarity) when a segment's line n.q = d (texture coordinates
    q = (p - foe) / s) passes its centre: t = tau0 (1 - d / n.(p - foe)), provided the crossing
    point lies on the segment. Exact times (floored to µs), no noise, no occlusion; ground truth
    v = (p - foe) / (tau0 - t) (:class:`ExpansionTruth`).
    """
    rng = np.random.default_rng(seed)
    tau0 = t_collision_s
    s_end = tau0 / (tau0 - seconds)
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width]
    px = (xs.ravel() - foe[0]).astype(np.float64)
    py = (ys.ravel() - foe[1]).astype(np.float64)
    half = np.array([geometry.width, geometry.height], float) * 0.6
    xs_out, ys_out, ts_out, ps_out = [], [], [], []
    for _ in range(n_segments):
        ang = rng.uniform(0, np.pi)
        nx, ny = np.cos(ang), np.sin(ang)
        centre = rng.uniform(-half, half)
        length = rng.uniform(4.0, 40.0)
        d = nx * centre[0] + ny * centre[1]
        if abs(d) < 1e-6:
            continue
        along0 = -ny * centre[0] + nx * centre[1]
        w = nx * px + ny * py
        with np.errstate(divide="ignore", invalid="ignore"):
            s = w / d
        hit = (s >= 1.0) & (s < s_end)
        if not hit.any():
            continue
        idx = np.nonzero(hit)[0]
        sh = s[idx]
        along = (-ny * px[idx] + nx * py[idx]) / sh
        on = np.abs(along - along0) <= 0.5 * length
        idx, sh = idx[on], sh[on]
        t = np.floor(tau0 * (1.0 - 1.0 / sh) * 1e6).astype(np.int64)
        xs_out.append(xs.ravel()[idx])
        ys_out.append(ys.ravel()[idx])
        ts_out.append(t)
        ps_out.append(np.full(len(idx), rng.choice([-1, 1]), np.int8))
    x = np.concatenate(xs_out).astype(np.uint16)
    y = np.concatenate(ys_out).astype(np.uint16)
    t = np.concatenate(ts_out)
    p = np.concatenate(ps_out)
    order = np.lexsort((x, y, t))
    ev = EventPacket(geometry=geometry, t_start=0, t_end=int(seconds * 1e6), x=x[order],
                     y=y[order], t=t[order], p=p[order])
    return ev.validate("expanding scene"), ExpansionTruth(foe, t_collision_s)


def _reference_stream(seconds: float):
    """(events, truth, label): the simulator's reference scene if available, else synthetic."""
    try:
        from evchain.core.registry import make_registry

        reg = make_registry()
        if "scene" in reg.filters and "emulator" in reg.filters:
            from evchain.core.chain import Chain
            from evchain.core.config import pipeline_from_text

            text = ("chain:\n  - use: scene\n  - use: emulator\n")
            spec = pipeline_from_text(text, "<flow-plane-bench>", reg)
            ctx = Context(seed=0)
            chain = Chain(spec, ctx)
            chain.setup()
            parts = []
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
                return ev, ctx.truth, "scene+emulator (defaults)"
    except Exception as exc:  # the simulator is optional here; fall back, and say so
        label = f"synthetic expanding scene (scene/emulator failed: {type(exc).__name__})"
        ev, truth = expanding_scene_events(seconds)
        return ev, truth, label
    ev, truth = expanding_scene_events(seconds)
    return ev, truth, "synthetic expanding scene (scene/emulator not available)"


def _packets(ev: EventPacket, packet_us: int = 10_000) -> list[EventPacket]:
    cuts = list(range(ev.t_start + packet_us, ev.t_end, packet_us))
    return recut([ev], cuts)


def _run(packets, params):
    f = PlaneFlow()
    f.setup(PlaneFlow.Params(**params), Context(geometry=packets[0].geometry))
    outs = [f.process(p) for p in packets]
    last = f.flush()
    if last is not None:
        outs.append(last)
    return outs


def _rows(workload: str, packets, truth, params, error_key: str, quick: bool,
          extra: dict) -> list[BenchRow]:
    n_in = sum(len(p) for p in packets)
    rows = []
    for variant in VARIANTS:
        prm = {**params, "variant": variant}
        outs = _run(packets, prm)
        secs = best_time(lambda prm=prm: _run(packets, prm), repeat=1 if quick else 3)
        x, y, t, vx, vy = (np.concatenate([getattr(o, c) for o in outs])
                           for c in ("x", "y", "t", "vx", "vy"))
        m = score_flow(x, y, t, vx, vy, truth)
        err = m[error_key]
        rows.append(BenchRow(
            workload=f"flow-plane-{SHORT[variant]}-{workload}", stage="plane_flow",
            throughput=n_in / secs, unit="ev/s", error=err, error_name=error_key,
            extra={**extra, "events_in": n_in, "density": len(x) / n_in if n_in else None,
                   "aee_pxs": m["aee_pxs"], "aee_normal_pxs": m["aee_normal_pxs"],
                   "aae_deg": m["aae_deg"], "invalid_rate": m["invalid_rate"],
                   "ree_pct": m["ree_pct"], "n_scored": m["n_scored"], "params": prm}))
    return rows


def bench_square(quick: bool) -> list[BenchRow]:
    path = DATA / "TranslatingSquare.aedat"
    if not path.is_file():
        return []
    from evchain.io.aedat2 import read_aedat2
    from evchain.io.dvsflow16 import DVSFLOW16Truth

    ev = read_aedat2(path, chip="davis240")
    truth = DVSFLOW16Truth(DATA / "gtTranslatingSquare.mat", 180, 240)
    params = dict(search_distance=2, window_us=100_000, refractory_us=0)
    return _rows("square", _packets(ev), truth, params, "aee_pxs", quick,
                 {"data": "DVSFLOW16 TranslatingSquare"})


def bench_reference(quick: bool) -> list[BenchRow]:
    seconds = 2.0 if quick else 10.0
    ev, truth, label = _reference_stream(seconds)
    return _rows("reference", _packets(ev), truth, REFERENCE_PARAMS, "invalid_rate", quick,
                 {"scene": label, "seconds": seconds})


WORKLOADS = {"flow-plane-square": bench_square, "flow-plane-reference": bench_reference}
