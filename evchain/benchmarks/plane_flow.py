"""Benchmarks of ``plane_flow``: rows ``flow-plane-<variant>-<workload>``.

Variants: ``single``, ``iterative``, ``robust``, ``original``, ``sg`` (``savitzky_golay``).

* ``square`` (workload ``flow-plane-square``): the DVSFLOW16 translating square
  (``../shared/data/dvsflow16``; no rows when absent); error = AEE (px/s) against the file's
  ground truth, window 100 ms, no refractory.
* ``reference`` (``flow-plane-reference``): the first 10 s (2 s with ``--quick``) of the
  reference drive as pipelines/reference.yaml renders it (a cached input, :func:`reference_input`:
  ``evchain bench --prepare flow-plane-reference`` makes it), with the thesis's selected
  parameters (search distance 2, window 80 ms, refractory 150 ms), not the pipelines'; error =
  invalid rate (0-1) against the scene's exact FOE, AEE in ``extra``. Without ``--quick`` also
  ``reference-nocheck``: the same without the centre check and with jAER's th2 (jAER's
  behaviour).
* ``expanding`` (``flow-plane-expanding``): the same rows on a synthetic expanding scene
  (:func:`expanding_scene_events`, 240x180, 10 s, 2 s with ``--quick``), made in the run.

Throughput = input events / s of the filter's ``process`` over 10 ms packets, one thread, from
the thread's CPU time (the machine is shared; ``extra["throughput_wall_eps"]`` has wall time).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_cpu_time, best_time, cut_every
from evchain.bench_cache import BenchInput, Workload
from evchain.benchmarks.drive_inputs import PIPELINES, drive_events, load_events
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.filters.flow_scorer import score_flow
from evchain.filters.plane_flow import PlaneFlow
from evchain.testing.contract import run_filter
from evchain.testing.synthetic import ExpansionTruth

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dvsflow16"
VARIANTS = ("single", "iterative", "robust", "original", "savitzky_golay")
SHORT = {"single": "single", "iterative": "iterative", "robust": "robust",
         "original": "original", "savitzky_golay": "sg"}
#: the thesis's selection with jAER's surface updates and a fixed window, whatever the camera
#: (the filter's defaults keep burst onsets, adapt the window to slow edges and derive times
#: and the speed ceiling from the focal length)
FIXED = dict(refractory_updates=True, max_window_us=0, th2_s=0.004, max_speed_pxs=1000.0)
REFERENCE_PARAMS = dict(search_distance=2, window_us=80_000, refractory_us=150_000, **FIXED)
#: jAER's behaviour for comparison: no centre check, jAER's 2016 th2 (scale differs, see docs)
THESIS_PARAMS = dict(REFERENCE_PARAMS, centre_check=False, th2_s=0.05)


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


def reference_input(quick: bool) -> BenchInput:
    """The events of the reference drive's first 10 s (``quick``: 2 s), as made by
    pipelines/reference.yaml's ``scene`` and ``emulator``: shared by the ``flow-*-reference``
    rows of both flow benchmarks."""
    return drive_events(PIPELINES / "reference.yaml", 0.0, 2.0 if quick else 10.0)


def reference_stream(quick: bool):
    """(events, exact ground truth, ``data`` string) of :func:`reference_input`."""
    inp = reference_input(quick)
    packets, ctx = load_events(inp)
    return EventPacket.concat(packets), ctx.truth, inp.describe()


def expanding_seconds(quick: bool) -> float:
    return 2.0 if quick else 10.0


def expanding_data(quick: bool) -> str:
    return f"synthetic expanding scene 240x180, {expanding_seconds(quick):g} s, no noise"


def _plane(params, packets):
    """One pass of ``PlaneFlow`` with ``params`` over ``packets`` (process, then flush)."""
    f = PlaneFlow()
    f.setup(PlaneFlow.Params(**params), Context(geometry=packets[0].geometry))
    return run_filter(f, packets, check=False)


def flow_row(workload: str, stage: str, run, packets, truth, error_key: str, quick: bool,
             extra: dict, data: str) -> BenchRow:
    """One benchmark row of a flow filter: ``run()`` processes ``packets`` (``data`` says what
    they are) and returns the output packets. Throughput = input events per CPU second of this
    thread (best of 1 or 3); the wall-clock rate and the flow metrics against ``truth`` go into
    ``extra``."""
    n_in = sum(len(p) for p in packets)
    outs = run()
    secs = best_cpu_time(run, repeat=1 if quick else 3, warmup=True, clock=time.thread_time)
    wall = best_time(run, repeat=1)
    x, y, t, vx, vy = (np.concatenate([getattr(o, c) for o in outs])
                       for c in ("x", "y", "t", "vx", "vy"))
    m = score_flow(x, y, t, vx, vy, truth)
    return BenchRow(
        workload=workload, stage=stage, throughput=n_in / secs, unit="ev/s",
        error=m[error_key], error_name=error_key,
        extra={**extra, "events_in": n_in, "throughput_wall_eps": n_in / wall,
               "flow_events": int(len(x)), "density": len(x) / n_in if n_in else None,
               "aee_pxs": m["aee_pxs"], "aee_normal_pxs": m["aee_normal_pxs"],
               "aae_deg": m["aae_deg"], "invalid_rate": m["invalid_rate"],
               "ree_pct": m["ree_pct"], "n_scored": m["n_scored"]}, data=data)


def _rows(workload: str, packets, truth, params, error_key: str, quick: bool,
          data: str) -> list[BenchRow]:
    rows = []
    for variant in VARIANTS:
        prm = {**params, "variant": variant}
        rows.append(flow_row(f"flow-plane-{SHORT[variant]}-{workload}", "plane_flow",
                             lambda prm=prm: _plane(prm, packets), packets, truth, error_key,
                             quick, {"params": prm}, data))
    return rows


def bench_square(quick: bool) -> list[BenchRow]:
    path = DATA / "TranslatingSquare.aedat"
    if not path.is_file():
        return []
    from evchain.io.aedat2 import read_aedat2
    from evchain.io.dvsflow16 import DVSFLOW16Truth

    ev = read_aedat2(path, chip="davis240")
    truth = DVSFLOW16Truth(DATA / "gtTranslatingSquare.mat", 180, 240)
    params = dict(search_distance=2, window_us=100_000, refractory_us=0, **FIXED)
    return _rows("square", cut_every(ev), truth, params, "aee_pxs", quick,
                 "DVSFLOW16 TranslatingSquare, window 100 ms, no refractory")


def _reference_rows(workload: str, ev, truth, quick: bool, data: str) -> list[BenchRow]:
    packets = cut_every(ev)
    rows = _rows(workload, packets, truth, REFERENCE_PARAMS, "invalid_rate", quick,
                 f"{data}, thesis parameters")
    if not quick:  # the same without evchain's centre check: what jAER's fits give
        rows += _rows(f"{workload}-nocheck", packets, truth, THESIS_PARAMS, "invalid_rate",
                      quick, f"{data}, thesis parameters without the centre check")
    return rows


def bench_reference(quick: bool) -> list[BenchRow]:
    ev, truth, data = reference_stream(quick)
    return _reference_rows("reference", ev, truth, quick, data)


def bench_expanding(quick: bool) -> list[BenchRow]:
    ev, truth = expanding_scene_events(expanding_seconds(quick))
    return _reference_rows("expanding", ev, truth, quick, expanding_data(quick))


WORKLOADS = {"flow-plane-square": bench_square,
             "flow-plane-reference": Workload(bench_reference, lambda q: [reference_input(q)]),
             "flow-plane-expanding": bench_expanding}
