"""Benchmarks of ``plane_flow``: rows ``flow-plane-<variant>-<workload>``.

* ``square``: the DVSFLOW16 translating square (``../shared/data/dvsflow16``; skipped when
  absent); error = AEE (px/s) against the file's ground truth, window 100 ms, no refractory.
* ``reference``: 10 s of the reference scene with the thesis's selected parameters (search
  distance 2, window 80 ms, refractory 150 ms); error = invalid rate (0-1) against the
  ground-truth FOE, AEE in ``extra``. Uses the ``scene`` source and the ``emulator`` when both are
  registered, else :func:`expanding_scene_events` (a synthetic expanding scene; the row's
  ``extra["scene"]`` says which).

Throughput = input events / s of the filter's ``process`` over 10 ms packets, one thread, from
the thread's CPU time (the machine is shared; ``extra["throughput_wall_eps"]`` has wall time).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from evchain.bench import (
    SIMULATOR_SOURCES,
    BenchRow,
    best_cpu_time,
    best_time,
    cut_every,
    source_stamp,
)
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
REFERENCE_PARAMS = dict(search_distance=2, window_us=80_000, refractory_us=150_000)
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


class TableTruth:
    """Ground truth sampled at given events: ``flow`` looks up the exact (x, y, t) of an event
    (NaN for anything else); ``foe`` interpolates FOE samples over time."""

    def __init__(self, x, y, t, vx, vy, foe_t, foe_x, foe_y, width: int, height: int):
        self.width, self.height = int(width), int(height)
        key = self._key(x, y, t)
        order = np.argsort(key, kind="stable")
        self.keys = key[order]
        self.vx = np.asarray(vx, np.float64)[order]
        self.vy = np.asarray(vy, np.float64)[order]
        self.foe_t = np.asarray(foe_t, np.float64)
        self.foe_x = np.asarray(foe_x, np.float64)
        self.foe_y = np.asarray(foe_y, np.float64)

    def _key(self, x, y, t):
        t = np.asarray(t, np.int64)
        return (t * self.height + np.asarray(y, np.int64)) * self.width + np.asarray(x, np.int64)

    def flow(self, x, y, t_us):
        key = self._key(np.rint(x), np.rint(y), np.rint(t_us))
        i = np.clip(np.searchsorted(self.keys, key), 0, len(self.keys) - 1)
        hit = self.keys[i] == key
        return np.where(hit, self.vx[i], np.nan), np.where(hit, self.vy[i], np.nan)

    def foe(self, t_us):
        t = np.asarray(t_us, np.float64)
        return (np.interp(t, self.foe_t, self.foe_x), np.interp(t, self.foe_t, self.foe_y))


CACHE = Path("/tmp/evchain-bench-cache")
REFERENCE_CHAIN = """
chain:
  - use: scene
    scenario: high-rise
    speed_mps: 20
    duration_s: {seconds}
  - use: emulator
    log_mapping: thesis8bit
    threshold_on: 20
    threshold_off: 20
"""


def make_reference_cache(seconds: float = 10.0, path: Path | None = None,
                         events_file: Path | None = None) -> Path:
    """Store the thesis reference drive's events (high-rise, 20 m/s, threshold 20 on the 8-bit
    log scale) of the first ``seconds`` with their exact flow and the FOE. The events come from
    ``events_file`` (the AEDAT file of ``evchain run pipelines/reference.yaml``) or are made by
    running ``scene`` + ``emulator`` (slow: the renderer is far from real time)."""
    from evchain.core.chain import Chain
    from evchain.core.config import pipeline_from_text
    from evchain.core.registry import make_registry

    path = path or CACHE / f"reference_{seconds:g}s_{source_stamp(*SIMULATOR_SOURCES)}.npz"
    reg = make_registry()
    spec = pipeline_from_text(REFERENCE_CHAIN.format(seconds=seconds), "<flow-plane-bench>", reg)
    ctx = Context(seed=0)
    chain = Chain(spec, ctx)
    chain.setup()  # the scene's ground truth is analytic: setting up renders nothing
    try:
        if events_file is None:
            packets = [p for p in chain.stream() if len(p)]
        else:
            from evchain.io.aedat2 import AedatSource
            from evchain.testing.contract import run_source

            got, _ = run_source(AedatSource, {"path": str(events_file)}, Path(events_file).parent)
            packets = [p.select(p.t < seconds * 1e6) for p in got if p.t_start < seconds * 1e6]
    finally:
        chain.close()
    ev = EventPacket.concat(packets)
    vx, vy = ctx.truth.flow(ev.x.astype(float), ev.y.astype(float), ev.t.astype(float))
    t_foe = np.arange(0, int(seconds * 1e6), 10_000, dtype=np.int64)
    fx, fy = ctx.truth.foe(t_foe.astype(float))
    g = ctx.geometry
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial.npz")
    np.savez(tmp, x=ev.x, y=ev.y, t=ev.t, p=ev.p, vx=vx, vy=vy,
             foe=np.column_stack([t_foe, fx, fy]).astype(np.float64),
             geometry=np.array([g.width, g.height]), seconds=seconds)
    tmp.replace(path)
    return path


def load_reference_cache(path: Path):
    d = np.load(path)
    w, h = (int(v) for v in d["geometry"])
    g = Geometry(w, h)
    ev = EventPacket(geometry=g, t_start=0, t_end=int(float(d["seconds"]) * 1e6),
                     x=d["x"].astype(np.uint16), y=d["y"].astype(np.uint16),
                     t=d["t"].astype(np.int64), p=d["p"].astype(np.int8))
    foe = d["foe"]
    truth = TableTruth(d["x"], d["y"], d["t"], d["vx"], d["vy"], foe[:, 0], foe[:, 1], foe[:, 2],
                       w, h)
    return ev, truth


def reference_stream(seconds: float):
    """(events, truth, label): the simulator's reference scene from the cache written by
    :func:`make_reference_cache` with this code (``seconds`` long, else the longest cached
    stretch), else the synthetic expanding scene. The label says which."""
    stamp = source_stamp(*SIMULATOR_SOURCES)
    path = CACHE / f"reference_{seconds:g}s_{stamp}.npz"
    if not path.is_file():
        cached = sorted(CACHE.glob(f"reference_*s_{stamp}.npz"),
                        key=lambda p: float(p.stem.split("_")[1][:-1]))
        path = cached[-1] if cached else path
    if path.is_file():
        ev, truth = load_reference_cache(path)
        secs = (ev.t_end - ev.t_start) / 1e6
        return ev, truth, f"simulator reference scene (high-rise, 20 m/s), first {secs:g} s"
    ev, truth = expanding_scene_events(seconds)
    return ev, truth, ("synthetic expanding scene (no simulator cache; make it with "
                       "python -m evchain.benchmarks.flow_plane SECONDS)")


def _plane(params, packets):
    """One pass of ``PlaneFlow`` with ``params`` over ``packets`` (process, then flush)."""
    f = PlaneFlow()
    f.setup(PlaneFlow.Params(**params), Context(geometry=packets[0].geometry))
    return run_filter(f, packets, check=False)


def flow_row(workload: str, stage: str, run, packets, truth, error_key: str, quick: bool,
             extra: dict) -> BenchRow:
    """One benchmark row of a flow filter: ``run()`` processes ``packets`` and returns the
    output packets. Throughput = input events per CPU second of this thread (best of 1 or 3);
    the wall-clock rate and the flow metrics against ``truth`` go into ``extra``."""
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
               "ree_pct": m["ree_pct"], "n_scored": m["n_scored"]})


def _rows(workload: str, packets, truth, params, error_key: str, quick: bool,
          extra: dict) -> list[BenchRow]:
    rows = []
    for variant in VARIANTS:
        prm = {**params, "variant": variant}
        rows.append(flow_row(f"flow-plane-{SHORT[variant]}-{workload}", "plane_flow",
                             lambda prm=prm: _plane(prm, packets), packets, truth, error_key,
                             quick, {**extra, "params": prm}))
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
    return _rows("square", cut_every(ev), truth, params, "aee_pxs", quick,
                 {"data": "DVSFLOW16 TranslatingSquare"})


def bench_reference(quick: bool) -> list[BenchRow]:
    seconds = 2.0 if quick else 10.0
    ev, truth, label = reference_stream(seconds)
    packets = cut_every(ev)
    rows = _rows("reference", packets, truth, REFERENCE_PARAMS, "invalid_rate", quick,
                 {"scene": label})
    if not quick:  # the same without evchain's centre check: what jAER's fits give
        rows += _rows("reference-nocheck", packets, truth, THESIS_PARAMS, "invalid_rate", quick,
                      {"scene": label})
    return rows


WORKLOADS = {"flow-plane-square": bench_square, "flow-plane-reference": bench_reference}


if __name__ == "__main__":
    import sys

    print(make_reference_cache(float(sys.argv[1]) if len(sys.argv) > 1 else 10.0,
                               events_file=Path(sys.argv[2]) if len(sys.argv) > 2 else None))
