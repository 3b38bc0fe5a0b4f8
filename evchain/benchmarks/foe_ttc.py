"""FOE and TTC: ``foe_map`` and ``ttc`` on synthetic expansion flow, and the whole chain from
emulator output to TTC on the reference scene.

* ``foe-map``: flow events/s of ``foe_map`` (defaults: region A radius 60 px, an estimate every
  1 ms) on a 320x240 pure-expansion field, normal flow on random edge normals with 10 % noise;
  error = mean distance of the estimates to the true FOE after 0.2 s. ``limit_ratio`` = time of a
  plain numpy pass over the same columns / stage time.
* ``foe-map-cell2``: the same with ``cell_px`` 2 (2x2-pixel map cells).
* ``foe-map-reference-lk`` / ``-plane`` (and ``-cell2``): CPU-time flow events/s of ``foe_map``
  alone on the flow of the reference drive (flow computed once and cached); errors = FOE mean
  |dx| (extra: |dy|, stds) after 1 s.
* ``foe-map-pipeline-lk`` / ``-plane``: the same with ``foe_map`` as configured in
  pipelines/reference-*.yaml (tau 100 ms, an estimate every 10 ms).
* ``ttc-synthetic``: flow events/s of ``ttc`` on an approach (tau = 3 s - t) with the true FOE in
  the ``foe`` series; error = median relative TTC error. The field is random points with exact
  flow and no moving edges, so tau comes from the flow's magnitude (``baseline_px`` 0).
* ``chain-reference-lk`` / ``chain-reference-plane``: events/s (emulator output events) of
  flow -> foe_map -> ttc on the reference scene (high-rise, 20 m/s, 320x240, threshold 20 on the
  thesis scale) over the last seconds before the obstacle; errors from ``foe_ttc_scorer`` (not
  timed): FOE mean |dx|, |dy| and the TTC median relative error over the last 3 s. The emulator
  output is rendered once and cached under ``$EVCHAIN_BENCH_CACHE`` (default
  ``/tmp/evchain-bench``): rendering takes minutes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from evchain.bench import SIMULATOR_SOURCES, BenchRow, best_cpu_time, best_time, source_stamp
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry, series_array
from evchain.testing.synthetic import approach_flow_packets

G = Geometry(320, 240, f=380.6)
CENTRE = (159.5, 119.5)


def _run(filters, packets):
    out = None
    for p in packets:
        for f in filters:
            p = f.process(p)
        out = p
    return out


def _foe_map_stage(packets, cell_px: int, params=None):
    """A fresh ``foe_map`` (``params``, else defaults with ``cell_px``) over ``packets``, and the
    list that collects its ``foe`` series entries (cleared at every call)."""
    from evchain.filters.foe_map import FoeMap

    series: list[np.ndarray] = []
    params = FoeMap.Params(cell_px=cell_px) if params is None else params

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
                      "estimate_every_us": 1000, "cell_px": cell_px,
                      "field": "320x240 normal flow, 10% noise"})]


def reference_flow(flow: str, start_m: float, duration_s: float):
    """Output of ``flow`` (thesis parameters = its defaults) on the cached reference events,
    cached as well (flow takes a while): (list of FlowPacket, context with the truth)."""
    from evchain.core.packets import FlowPacket
    from evchain.core.registry import make_registry

    events, ctx = reference_events(start_m, duration_s)
    stamp = source_stamp(*SIMULATOR_SOURCES, f"filters/{flow}.py", f"kernels/{flow}.py")
    path = _cache_dir() / f"reference-{start_m:g}m-{duration_s:g}s-{flow}-{stamp}.npz"
    if not path.exists():
        f = make_registry().get(flow)()
        f.id = flow
        f.setup(f.Params(), Context(seed=0, geometry=ctx.geometry, truth=ctx.truth))
        outs = [f.process(p) for p in events]
        last = f.flush()
        if last is not None:
            outs.append(last)
        cat = {c: np.concatenate([getattr(o, c) for o in outs])
               for c in ("x", "y", "t", "p", "vx", "vy")}
        tmp = path.with_name(path.name + ".partial.npz")
        np.savez(tmp, **cat, bounds=np.array([o.t_start for o in outs] + [outs[-1].t_end]))
        os.replace(tmp, path)
    with np.load(path) as f:
        d = {k: f[k] for k in ("x", "y", "t", "p", "vx", "vy", "bounds")}
    b = d["bounds"]
    idx = np.searchsorted(d["t"], b)
    packets = [FlowPacket(geometry=ctx.geometry, t_start=int(b0), t_end=int(b1),
                          **{c: d[c][i:j] for c in ("x", "y", "t", "p", "vx", "vy")})
               for b0, b1, i, j in zip(b[:-1], b[1:], idx[:-1], idx[1:], strict=True)]
    return packets, ctx


def foe_reference_rows(flow: str, quick: bool, cell_px: int = 1,
                       pipeline: bool = False) -> list[BenchRow]:
    """``foe_map`` alone (defaults, or as in pipelines/reference-*.yaml with ``pipeline``) on
    the flow of the reference drive's last 5 s (``quick``: 1 s); error = mean |dx|, |dy|
    against the true FOE after a 1 s warm-up (the scorer's)."""
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry
    from evchain.filters.foe_map import FoeMap

    start_m, dur = (220.0, 1.0) if quick else (180.0, 5.0)
    packets, ctx = reference_flow(flow, start_m, dur)
    n = sum(len(p) for p in packets)
    name = "lk" if flow == "lk_flow" else "plane"
    params = FoeMap.Params(cell_px=cell_px)
    if pipeline:
        spec = load_pipeline(PIPELINES / f"reference-{name}.yaml", make_registry())
        params = spec.stage("foe_map").params
    stage, series = _foe_map_stage(packets, cell_px, params)

    cpu = best_cpu_time(stage, repeat=3, warmup=True)
    s = np.concatenate(series)
    s = s[s["t"] >= packets[0].t_start + (1_000_000 if not quick else 200_000)]
    xt, yt = ctx.truth.foe(s["t"].astype(np.float64))
    adx, ady = np.abs(s["x"] - xt), np.abs(s["y"] - yt)
    name += "" if cell_px == 1 else f"-cell{cell_px}"
    row = f"foe-map-pipeline-{name}" if pipeline else f"foe-map-reference-{name}"
    return [BenchRow(row, "foe_map", n / cpu, "flow ev/s (CPU)",
                     float(adx.mean()), "foe_dx_mean_px", None,
                     {"events": n, "stretch": f"{start_m:g} m + {dur:g} s", "cell_px": cell_px,
                      "params": params.model_dump(),
                      "foe_dx_mean_px": float(adx.mean()), "foe_dx_std_px": float(adx.std()),
                      "foe_dy_mean_px": float(ady.mean()), "foe_dy_std_px": float(ady.std())})]


def foe_fit_reference_rows(flow: str, quick: bool) -> list[BenchRow]:
    """``foe_fit`` alone on the reference drive's last 5 s (``quick``: 1 s): the pipeline's flow
    and ``foe_map`` run once (not timed), then ``foe_fit`` as configured in
    pipelines/reference-*.yaml; error = mean |dy| against the true FOE after the warm-up (the
    vertical error is what it corrects), |dx| in the extras."""
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    start_m, dur = (220.0, 1.0) if quick else (180.0, 5.0)
    packets, ctx = reference_flow(flow, start_m, dur)
    n = sum(len(p) for p in packets)
    name = "lk" if flow == "lk_flow" else "plane"
    spec = load_pipeline(PIPELINES / f"reference-{name}.yaml", make_registry())

    def make(use):
        st = spec.stage(use)
        f = st.cls()
        f.setup(st.params, Context(seed=0, geometry=ctx.geometry))
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
    s = np.concatenate(series)
    s = s[s["t"] >= packets[0].t_start + (1_000_000 if not quick else 200_000)]
    xt, yt = ctx.truth.foe(s["t"].astype(np.float64))
    adx, ady = np.abs(s["x"] - xt), np.abs(s["y"] - yt)
    return [BenchRow(f"foe-fit-reference-{name}", "foe_fit", n / cpu, "flow ev/s (CPU)",
                     float(ady.mean()), "foe_dy_mean_px", None,
                     {"events": n, "stretch": f"{start_m:g} m + {dur:g} s",
                      "foe_dx_mean_px": float(adx.mean()), "foe_dx_std_px": float(adx.std()),
                      "foe_dy_mean_px": float(ady.mean()), "foe_dy_std_px": float(ady.std())})]


def ttc_rows(quick: bool) -> list[BenchRow]:
    from evchain.filters.foe_map import FOE_DTYPE
    from evchain.filters.ttc import Ttc

    n = 500_000 if quick else 2_000_000
    dur = 2_000_000
    packets = approach_flow_packets(foe=CENTRE, tau_s=3.0, n=n, geometry=G, duration_us=dur,
                                    n_packets=200, normal_only=True, noise_frac=0.1,
                                    tau_shrinks=True)
    packets = [p.with_series("foe", series_array(FOE_DTYPE, t=[p.t_start], x=[CENTRE[0]],
                                                 y=[CENTRE[1]], support=[1.0], total=[1.0]))
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
                     None, {"events": n, "throughput_cpu": n / cpu,
                            "field": "320x240 approach, normal flow, 10% noise",
                            "true_foe": True})]


# -- the whole chain on the reference scene ------------------------------------------------

def _cache_dir() -> Path:
    return Path(os.environ.get("EVCHAIN_BENCH_CACHE", "/tmp/evchain-bench"))


def reference_events(start_m: float, duration_s: float):
    """Emulator output of the reference drive from ``start_m`` for ``duration_s``, cached; plus
    the scene's geometry and ground truth (cheap: no rendering)."""
    from evchain.core.registry import make_registry

    reg = make_registry()
    ctx = Context(seed=0)
    scene = reg.get("scene")()
    scene.id = "scene"
    scene.setup(scene.Params(scenario="high-rise", speed_mps=20, width=320, height=240,
                             supersample=2, fov_deg=35, max_motion_px=0.5, start_m=start_m,
                             duration_s=duration_s), ctx)
    stamp = source_stamp(*SIMULATOR_SOURCES)
    path = _cache_dir() / f"reference-{start_m:g}m-{duration_s:g}s-{stamp}.npz"
    if not path.exists():
        emu = reg.get("emulator")()
        emu.id = "emulator"
        emu.setup(emu.Params(threshold_on=20, threshold_off=20, log_mapping="thesis8bit",
                             mismatch_sigma=0), ctx)
        evs = [emu.process(p) for p in scene.packets()]
        last = emu.flush()
        if last is not None:
            evs.append(last)
        ev = EventPacket.concat(evs)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".partial.npz")
        np.savez(tmp, x=ev.x, y=ev.y, t=ev.t, p=ev.p,
                 bounds=np.array([e.t_start for e in evs] + [evs[-1].t_end]))
        os.replace(tmp, path)
    with np.load(path) as f:  # every d[key] of an NpzFile reads the array again: once each
        d = {k: f[k] for k in ("x", "y", "t", "p", "bounds")}
    b = d["bounds"]
    idx = np.searchsorted(d["t"], b)
    packets = [EventPacket(geometry=ctx.geometry, t_start=int(b0), t_end=int(b1),
                           x=d["x"][i:j], y=d["y"][i:j], t=d["t"][i:j], p=d["p"][i:j])
               for b0, b1, i, j in zip(b[:-1], b[1:], idx[:-1], idx[1:], strict=True)]
    scene.close()
    return packets, ctx


#: the chain rows run the stages of these pipelines that follow the emulator, as configured there
PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
SCORERS = ("flow_scorer", "foe_ttc_scorer")


def chain_rows(flow: str, quick: bool) -> list[BenchRow]:
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    start_m, dur = (220.0, 1.0) if quick else (180.0, 5.0)
    events, ctx = reference_events(start_m, dur)
    n_events = sum(len(p) for p in events)
    reg = make_registry()
    name = "lk" if flow == "lk_flow" else "plane"
    spec = load_pipeline(PIPELINES / f"reference-{name}.yaml", reg)
    uses = [s.use for s in spec.stages]
    stages = spec.stages[uses.index("emulator") + 1:]

    def build(with_scorer: bool):
        fs = []
        for st in stages:
            if st.use in SCORERS and not with_scorer:
                continue
            f = st.cls()
            f.id = st.id
            params = st.params
            if st.use == "foe_ttc_scorer":
                params = params.model_copy(update={"plots": False})
            f.setup(params, Context(seed=0, geometry=ctx.geometry, truth=ctx.truth,
                                    metrics=ctx.metrics))
            fs.append(f)
        return fs

    def stage():
        fs = build(False)
        _run(fs, events)
        for f in fs:
            f.flush()

    t = best_time(stage, repeat=1 if not quick else 2)
    cpu = best_cpu_time(stage, repeat=1)
    fs = build(True)  # once more with the scorer (not timed) for the errors
    _run(fs, events)
    for f in fs:
        f.flush()
    fm, tm = ctx.metrics.get("foe", {}), ctx.metrics.get("ttc", {})
    timed = "+".join(st.use for st in stages if st.use not in SCORERS)
    return [BenchRow(f"chain-reference-{name}", timed, n_events / t, "events/s",
                     tm.get("median_rel_error_last3s"), "ttc_median_rel_err_last3s", None,
                     {"events": n_events, "throughput_cpu": n_events / cpu,
                      "stretch": f"{start_m:g} m + {dur:g} s",
                      "foe_dx_mean_px": fm.get("dx_mean_px"),
                      "foe_dy_mean_px": fm.get("dy_mean_px"),
                      "foe_dx_std_px": fm.get("dx_std_px"),
                      "foe_dy_std_px": fm.get("dy_std_px"),
                      "ttc_share_on_obstacle_within_20pct":
                          tm.get("share_on_obstacle_within_20pct"),
                      "ttc_share_within_20pct": tm.get("share_within_20pct"),
                      "ttc_share_within_10pct": tm.get("share_within_10pct")})]


WORKLOADS = {
    "foe-map": foe_map_rows,
    "foe-map-cell2": lambda quick: foe_map_rows(quick, cell_px=2),
    "foe-map-reference-lk": lambda quick: foe_reference_rows("lk_flow", quick),
    "foe-map-reference-plane": lambda quick: foe_reference_rows("plane_flow", quick),
    "foe-map-reference-lk-cell2": lambda quick: foe_reference_rows("lk_flow", quick, 2),
    "foe-map-reference-plane-cell2": lambda quick: foe_reference_rows("plane_flow", quick, 2),
    "foe-map-pipeline-lk": lambda quick: foe_reference_rows("lk_flow", quick, pipeline=True),
    "foe-map-pipeline-plane": lambda quick: foe_reference_rows("plane_flow", quick,
                                                               pipeline=True),
    "foe-fit-reference-lk": lambda quick: foe_fit_reference_rows("lk_flow", quick),
    "foe-fit-reference-plane": lambda quick: foe_fit_reference_rows("plane_flow", quick),
    "ttc-synthetic": ttc_rows,
    "chain-reference-lk": lambda quick: chain_rows("lk_flow", quick),
    "chain-reference-plane": lambda quick: chain_rows("plane_flow", quick),
}
