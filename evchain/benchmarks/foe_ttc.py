"""FOE and TTC: ``foe_map`` and ``ttc`` on synthetic expansion flow, ``foe_map`` and ``foe_fit``
on the flow of the reference drive, and the whole chain from emulator output to TTC.

Synthetic (made in the run, no cached input):

* ``foe-map``: flow events/s of ``foe_map`` (defaults: region A radius 60 px, an estimate every
  1 ms) on a 320x240 pure-expansion field, normal flow on random edge normals with 10 % noise;
  error = mean distance of the estimates to the true FOE after 0.2 s. ``limit_ratio`` = time of a
  plain numpy pass over the same columns / stage time.
* ``foe-map-cell2``: the same with ``cell_px`` 2 (2x2-pixel map cells).
* ``ttc-synthetic``: flow events/s of ``ttc`` (defaults, ``baseline_px`` 0) on an approach
  (tau = 3 s - t) with the true FOE in the ``foe`` series; error = median relative TTC error.
  The field is random points with exact flow and no moving edges, so tau comes from the flow's
  magnitude.

On the reference drive's last 5 s before the obstacle (180 m + 5 s; ``--quick``: 220 m + 1 s),
cached inputs made by ``evchain bench --prepare`` (:mod:`evchain.benchmarks.drive_inputs`): the
events of the ``scene`` and ``emulator`` stages of pipelines/reference-lk.yaml or
reference-plane.yaml, and the flow of that pipeline's flow stage on them. Every stage parameter
these rows use beyond ``foe_map``'s defaults is read from that file (``params_from``):

* ``foe-map-reference-lk`` / ``-plane`` (and ``-cell2``): CPU-time flow events/s of ``foe_map``
  with its defaults alone on the pipeline's flow; error = FOE mean |dx| (extra: |dy|, stds)
  after 1 s (quick: 0.2 s).
* ``foe-map-pipeline-lk`` / ``-plane``: the same with ``foe_map`` as configured in the pipeline
  (tau 100 ms, an estimate every 10 ms).
* ``foe-fit-pipeline-lk`` / ``-plane``: ``foe_fit`` of the pipeline alone on the votes of the
  pipeline's ``foe_map`` (run once, not timed); error = FOE mean |dy|.
* ``foe-fit-pitch-lk`` / ``-plane``: the same on the drive pitching (``scene.dynamics=pitch``)
  with its simulated IMU (1 kHz, 0.1 deg/s noise: pipelines/sweeps/evaluation-gyro.yaml's), two
  rows side by side on the same flow: ``foe-fit-pitch-*`` fits the rotation to the flow (the
  default), ``foe-fit-pitch-gyro-*`` takes it from the gyro (``rotation_source: imu``); extras:
  |dx| and the median rotation rate error (deg/s).
* ``chain-reference-lk`` / ``-plane``: events/s (emulator output events, per wall second) of
  the pipeline's stages after the emulator (flow -> foe_map -> foe_fit -> ttc) on one thread;
  ``chain-reference-lk-threads`` / ``-plane-threads``: the same with each stage on a thread of
  its own, as ``evchain run`` runs them (:mod:`evchain.core.stage_threads`), the two measured
  alternately in one run; ``throughput_cpu`` per CPU second of all threads. Errors from the
  pipeline's ``foe_ttc_scorer`` (not timed; the same for both): TTC median relative error over
  the last 3 s, FOE mean |dx|, |dy| in the extras.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_cpu_time, best_time
from evchain.bench_cache import BenchInput, Workload
from evchain.benchmarks.drive_inputs import (
    PIPELINES,
    drive_events,
    drive_flow,
    load_events,
    load_flow,
    relative,
)
from evchain.core.filter import Context
from evchain.core.packets import Geometry
from evchain.core.stage_threads import in_order, in_threads
from evchain.testing.synthetic import approach_flow_packets

G = Geometry(320, 240, f=380.6)
#: foe_map's settings in the foe-map rows (the filter's defaults read every 10 ms and decay
#: with 100 ms; the rows keep the heavier load they have always measured)
ROW_SETTINGS = {"tau_ms": 300.0, "estimate_every_us": 1000}
CENTRE = (159.5, 119.5)


def _foe_map_stage(packets, cell_px: int, params=None):
    """A fresh ``foe_map`` (``params``, else defaults with ``cell_px``) over ``packets``, and the
    list that collects its ``foe`` series entries (cleared at every call)."""
    from evchain.filters.foe_map import FoeMap

    series: list[np.ndarray] = []
    params = FoeMap.Params(**ROW_SETTINGS, cell_px=cell_px) if params is None else params

    def stage():
        f = FoeMap()
        f.setup(params, Context())
        series.clear()
        for p in packets:
            series.append(f.process(p).series["foe"])

    return stage, series


def foe_map_rows(quick: bool, cell_px: int = 1) -> list[BenchRow]:
    n = 1_000_000 if quick else 4_000_000
    dur = n  # 1 M flow events per second of stream
    packets = approach_flow_packets(foe=CENTRE, tau_s=5.0, n=n, geometry=G, duration_us=dur,
                                    n_packets=max(1, dur // 10_000), normal_only=True,
                                    noise_frac=0.1)
    stage, series = _foe_map_stage(packets, cell_px)

    t = best_time(stage, repeat=3)
    cpu = best_cpu_time(stage, repeat=2)
    s = np.concatenate(series)
    s = s[s["t"] >= 200_000]
    err = float(np.mean(np.hypot(s["x"] - CENTRE[0], s["y"] - CENTRE[1])))
    cols = [np.concatenate([getattr(p, c) for p in packets]) for c in ("x", "y", "t", "vx",
                                                                       "vy")]
    t_limit = best_time(lambda: [c.sum() for c in cols], repeat=3)
    name = "foe-map" if cell_px == 1 else f"foe-map-cell{cell_px}"
    return [BenchRow(name, "foe_map", n / t, "flow ev/s", err, "foe_err_px", t_limit / t,
                     {"events": n, "throughput_cpu": n / cpu, "region_radius_px": 60,
                      "estimate_every_us": 1000, "cell_px": cell_px},
                     data=f"synthetic expansion 320x240, {n / 1e6:g} M normal-flow events, "
                          f"10 % noise; foe_map with 1 ms reads and 300 ms decay, cell_px "
                          f"{cell_px}")]


def stretch(quick: bool) -> tuple[float, float]:
    """(start_m, duration_s) of the drive the reference rows run on: the last 5 s before the
    obstacle (``quick``: 1 s at 220 m)."""
    return (220.0, 1.0) if quick else (180.0, 5.0)


def pipeline_file(flow: str) -> Path:
    return PIPELINES / f"reference-{'lk' if flow == 'lk_flow' else 'plane'}.yaml"


def flow_input(flow: str, quick: bool) -> BenchInput:
    """The flow of pipelines/reference-*.yaml's flow stage on :func:`stretch` of its drive."""
    return drive_flow(pipeline_file(flow), *stretch(quick))


def events_input(flow: str, quick: bool) -> BenchInput:
    """The events of :func:`stretch` of the drive of pipelines/reference-*.yaml."""
    return drive_events(pipeline_file(flow), *stretch(quick))


def _pipeline(flow: str, overrides: tuple[str, ...] = ()):
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    return load_pipeline(pipeline_file(flow), make_registry(), list(overrides))


def _after_warmup(series: list[np.ndarray], t_start: int, quick: bool) -> np.ndarray:
    """The FOE estimates after the warm-up (1 s; ``quick``: 0.2 s), joined."""
    s = np.concatenate(series)
    return s[s["t"] >= t_start + (1_000_000 if not quick else 200_000)]


def _foe_errors(series: list[np.ndarray], t_start: int, quick: bool, truth):
    """|dx|, |dy| of the FOE estimates after the warm-up."""
    s = _after_warmup(series, t_start, quick)
    xt, yt = truth.foe(s["t"].astype(np.float64))
    return np.abs(s["x"] - xt), np.abs(s["y"] - yt)


def foe_reference_rows(flow: str, quick: bool, cell_px: int = 1,
                       pipeline: bool = False) -> list[BenchRow]:
    """``foe_map`` alone (its defaults with ``cell_px``, or with ``pipeline`` as configured in
    pipelines/reference-*.yaml) on the flow of that pipeline's flow stage over the drive's last
    5 s (``quick``: 1 s); error = mean |dx|, |dy| against the true FOE after a 1 s warm-up (the
    scorer's)."""
    from evchain.filters.foe_map import FoeMap

    inp = flow_input(flow, quick)
    packets, ctx = load_flow(inp)
    n = sum(len(p) for p in packets)
    name = "lk" if flow == "lk_flow" else "plane"
    if pipeline:
        params = _pipeline(flow).stage("foe_map").params
        how = "foe_map of the pipeline"
    else:
        params = FoeMap.Params(**ROW_SETTINGS, cell_px=cell_px)
        how = f"foe_map with 1 ms reads and 300 ms decay, cell_px {cell_px}"
    stage, series = _foe_map_stage(packets, cell_px, params)

    cpu = best_cpu_time(stage, repeat=3, warmup=True)
    adx, ady = _foe_errors(series, packets[0].t_start, quick, ctx.truth)
    name += "" if cell_px == 1 else f"-cell{cell_px}"
    row = f"foe-map-pipeline-{name}" if pipeline else f"foe-map-reference-{name}"
    return [BenchRow(row, "foe_map", n / cpu, "flow ev/s (CPU)",
                     float(adx.mean()), "foe_dx_mean_px", None,
                     {"events": n, "stretch": "{:g} m + {:g} s".format(*stretch(quick)),
                      "cell_px": cell_px, "params": {"foe_map": params.model_dump(mode="json")},
                      "foe_dx_mean_px": float(adx.mean()), "foe_dx_std_px": float(adx.std()),
                      "foe_dy_mean_px": float(ady.mean()), "foe_dy_std_px": float(ady.std())},
                     data=f"{inp.describe()}; {how}",
                     params_from=relative(pipeline_file(flow)))]


def foe_fit_pipeline_rows(flow: str, quick: bool) -> list[BenchRow]:
    """``foe_fit`` alone on the drive's last 5 s (``quick``: 1 s): the pipeline's flow and
    ``foe_map`` run once (not timed), then ``foe_fit``, all as configured in
    pipelines/reference-*.yaml; error = mean |dy| against the true FOE after the warm-up (the
    vertical error is what it corrects), |dx| in the extras."""
    name = "lk" if flow == "lk_flow" else "plane"
    inp = flow_input(flow, quick)
    return [_foe_fit_row(f"foe-fit-pipeline-{name}", inp, load_flow(inp), _pipeline(flow),
                         flow, quick)]


#: the pitching drive of the ``foe-fit-pitch`` rows: the evaluation's pitch cell with its IMU
#: (pipelines/sweeps/evaluation-gyro.yaml)
PITCH = ("scene.dynamics=pitch", "scene.imu_rate_hz=1000", "scene.imu_gyro_noise_dps=0.1")


def pitch_flow_input(flow: str, quick: bool) -> BenchInput:
    """The flow of pipelines/reference-*.yaml's flow stage on :func:`stretch` of its drive
    pitching (:data:`PITCH`), the packets with the scene's IMU."""
    return drive_flow(pipeline_file(flow), *stretch(quick), PITCH)


def foe_fit_pitch_rows(flow: str, quick: bool) -> list[BenchRow]:
    """``foe_fit`` of the pipeline alone on a pitching drive, its rotation fitted to the flow
    (``foe-fit-pitch-*``, the default) and taken from the gyro (``foe-fit-pitch-gyro-*``,
    ``rotation_source: imu``), side by side on the same flow and votes; error = mean |dy|,
    |dx| and the median rotation rate error in the extras."""
    name = "lk" if flow == "lk_flow" else "plane"
    inp = pitch_flow_input(flow, quick)
    loaded = load_flow(inp)   # once for both rows: foe_fit leaves its input unchanged
    return [_foe_fit_row(f"foe-fit-pitch-{name}", inp, loaded, _pipeline(flow, PITCH), flow,
                         quick),
            _foe_fit_row(f"foe-fit-pitch-gyro-{name}", inp, loaded,
                         _pipeline(flow, (*PITCH, "foe_fit.rotation_source=imu")), flow, quick)]


def _foe_fit_row(row: str, inp: BenchInput, loaded, spec, flow: str, quick: bool) -> BenchRow:
    """``foe_fit`` of ``spec`` on the flow ``inp`` (``loaded``: its packets and context) after
    ``spec``'s ``foe_map`` (not timed)."""
    packets, ctx = loaded
    n = sum(len(p) for p in packets)

    def make(use):
        st = spec.stage(use)
        f = st.cls()
        f.setup(st.params, Context(seed=spec.seed, geometry=ctx.geometry))
        return f

    foe_map = make("foe_map")
    voted = [foe_map.process(p) for p in packets]
    series: list[np.ndarray] = []

    def stage():
        f = make("foe_fit")
        series.clear()
        for p in voted:
            series.append(f.process(p).series["foe"])

    cpu = best_cpu_time(stage, repeat=1, warmup=True)
    adx, ady = _foe_errors(series, packets[0].t_start, quick, ctx.truth)
    params = {use: spec.stage(use).params.model_dump(mode="json")
              for use in ("foe_map", "foe_fit")}
    extra = {"events": n, "stretch": "{:g} m + {:g} s".format(*stretch(quick)),
             "params": params,
             "foe_dx_mean_px": float(adx.mean()), "foe_dx_std_px": float(adx.std()),
             "foe_dy_mean_px": float(ady.mean()), "foe_dy_std_px": float(ady.std())}
    rotation = _rotation_error(series, packets[0].t_start, quick, ctx.truth)
    if rotation is not None:
        extra["rotation_rate_error_deg_s"] = rotation
    return BenchRow(row, "foe_fit", n / cpu, "flow ev/s (CPU)", float(ady.mean()),
                    "foe_dy_mean_px", None, extra,
                    data=f"{inp.describe()}; foe_map and foe_fit of the pipeline",
                    params_from=relative(pipeline_file(flow)))


def _rotation_error(series: list[np.ndarray], t_start: int, quick: bool,
                    truth) -> float | None:
    """Median norm (deg/s) of the estimated minus the true angular velocity over the
    estimates after the warm-up that carry a rotation; None when none does."""
    from evchain.core.series import ROTATION_FIELDS

    s = _after_warmup(series, t_start, quick)
    s = s[s["rotation"] > 0]
    if not len(s):
        return None
    w = np.stack([s[c] for c in ROTATION_FIELDS], 1)
    wt = np.degrees(np.stack(truth.angular_velocity(s["t"].astype(np.float64)), 1))
    return float(np.median(np.linalg.norm(w - wt, axis=1)))


def ttc_rows(quick: bool) -> list[BenchRow]:
    from evchain.core.series import FOE
    from evchain.filters.ttc import Ttc

    n = 500_000 if quick else 2_000_000
    dur = 2_000_000
    packets = approach_flow_packets(foe=CENTRE, tau_s=3.0, n=n, geometry=G, duration_us=dur,
                                    n_packets=200, normal_only=True, noise_frac=0.1,
                                    tau_shrinks=True)
    packets = [p.with_series(FOE.name, FOE.array(t=[p.t_start], x=[CENTRE[0]], y=[CENTRE[1]],
                                                 support=[1.0], total=[1.0]))
               for p in packets]
    series = []

    def stage():
        f = Ttc()
        f.setup(Ttc.Params(baseline_px=0), Context())  # random points, no moving edges
        series.clear()
        for p in packets:
            series.append(f.process(p).series["ttc"])

    t = best_time(stage, repeat=3)
    cpu = best_cpu_time(stage, repeat=2)
    s = np.concatenate(series)
    truth = 3.0 - s["t"] * 1e-6
    err = float(np.median(np.abs(s["tau_s"] - truth) / truth))
    return [BenchRow("ttc-synthetic", "ttc", n / t, "flow ev/s", err, "ttc_median_rel_err",
                     None, {"events": n, "throughput_cpu": n / cpu, "true_foe": True},
                     data=f"synthetic approach 320x240, {n / 1e6:g} M normal-flow events, "
                          "10 % noise, true FOE; ttc defaults, baseline_px 0")]


# -- the whole chain on the reference scene ------------------------------------------------

#: the chain rows run the stages of pipelines/reference-*.yaml that follow the emulator,
#: scorers (``Filter.scorer``) untimed


def chain_rows(flow: str, quick: bool) -> list[BenchRow]:
    inp = events_input(flow, quick)
    events, ctx = load_events(inp)
    n_events = sum(len(p) for p in events)
    name = "lk" if flow == "lk_flow" else "plane"
    spec = _pipeline(flow)
    uses = [s.use for s in spec.stages]
    stages = spec.stages[uses.index("emulator") + 1:]

    def build(with_scorer: bool):
        fs = []
        for st in stages:
            if st.cls.scorer and not with_scorer:
                continue
            f = st.cls()
            f.id = st.id
            params = st.params
            if st.use == "foe_ttc_scorer":
                params = params.model_copy(update={"plots": False})
            f.setup(params, Context(seed=spec.seed, geometry=ctx.geometry, truth=ctx.truth,
                                    metrics=ctx.metrics))
            fs.append(f)
        return fs

    def timed(run):
        def stage():
            for _ in run(iter(events), build(False)):
                pass
        return stage

    # one thread and stage threads side by side: the two runs alternate, the best of each
    ways = {"": in_order, "-threads": in_threads}
    for run in ways.values():
        timed(run)()  # warm-up (compiles)
    wall = {k: float("inf") for k in ways}
    cpu = dict(wall)
    for _ in range(1 if quick else 2):
        for k, run in ways.items():
            t0, c0 = time.perf_counter(), time.process_time()
            timed(run)()
            wall[k] = min(wall[k], time.perf_counter() - t0)
            cpu[k] = min(cpu[k], time.process_time() - c0)
    for _ in in_order(iter(events), build(True)):  # once more with the scorer, for the errors
        pass
    fm, tm = ctx.metrics.get("foe", {}), ctx.metrics.get("ttc", {})
    timed_stages = "+".join(st.use for st in stages if not st.cls.scorer)
    extra = {"events": n_events, "stretch": "{:g} m + {:g} s".format(*stretch(quick)),
             "params": {st.id: st.params.model_dump(mode="json") for st in stages},
             "foe_dx_mean_px": fm.get("dx_mean_px"),
             "foe_dy_mean_px": fm.get("dy_mean_px"),
             "foe_dx_std_px": fm.get("dx_std_px"),
             "foe_dy_std_px": fm.get("dy_std_px"),
             "ttc_share_on_obstacle_within_20pct": tm.get("share_on_obstacle_within_20pct"),
             "ttc_share_within_20pct": tm.get("share_within_20pct"),
             "ttc_share_within_10pct": tm.get("share_within_10pct")}
    return [BenchRow(f"chain-reference-{name}{k}", timed_stages, n_events / wall[k],
                     "events/s", tm.get("median_rel_error_last3s"),
                     "ttc_median_rel_err_last3s", None,
                     {**extra, "threads": "stage threads" if k else "one",
                      "throughput_cpu": n_events / cpu[k],
                      "speedup_over_one_thread": wall[""] / wall[k]},
                     data=inp.describe(), params_from=relative(pipeline_file(flow)))
            for k in ways]


def _on_flow(flow: str, rows):
    return Workload(rows, lambda quick: [flow_input(flow, quick)])


def _on_events(flow: str, rows):
    return Workload(rows, lambda quick: [events_input(flow, quick)])


WORKLOADS = {
    "foe-map": foe_map_rows,
    "foe-map-cell2": lambda quick: foe_map_rows(quick, cell_px=2),
    "foe-map-reference-lk": _on_flow("lk_flow", lambda q: foe_reference_rows("lk_flow", q)),
    "foe-map-reference-plane": _on_flow("plane_flow",
                                        lambda q: foe_reference_rows("plane_flow", q)),
    "foe-map-reference-lk-cell2": _on_flow("lk_flow",
                                           lambda q: foe_reference_rows("lk_flow", q, 2)),
    "foe-map-reference-plane-cell2": _on_flow("plane_flow",
                                              lambda q: foe_reference_rows("plane_flow", q, 2)),
    "foe-map-pipeline-lk": _on_flow("lk_flow", lambda q: foe_reference_rows(
        "lk_flow", q, pipeline=True)),
    "foe-map-pipeline-plane": _on_flow("plane_flow", lambda q: foe_reference_rows(
        "plane_flow", q, pipeline=True)),
    "foe-fit-pipeline-lk": _on_flow("lk_flow", lambda q: foe_fit_pipeline_rows("lk_flow", q)),
    "foe-fit-pipeline-plane": _on_flow("plane_flow",
                                       lambda q: foe_fit_pipeline_rows("plane_flow", q)),
    "foe-fit-pitch-lk": Workload(lambda q: foe_fit_pitch_rows("lk_flow", q),
                                 lambda quick: [pitch_flow_input("lk_flow", quick)]),
    "foe-fit-pitch-plane": Workload(lambda q: foe_fit_pitch_rows("plane_flow", q),
                                    lambda quick: [pitch_flow_input("plane_flow", quick)]),
    "ttc-synthetic": ttc_rows,
    "chain-reference-lk": _on_events("lk_flow", lambda q: chain_rows("lk_flow", q)),
    "chain-reference-plane": _on_events("plane_flow", lambda q: chain_rows("plane_flow", q)),
}
