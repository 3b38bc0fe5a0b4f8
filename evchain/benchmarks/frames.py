"""Benchmarks of the frame baseline (pipelines/frames-reference.yaml: scene -> aps -> frame_flow
-> foe_lines), each stage with the pipeline's parameters on a stretch of the reference drive
shortly before the obstacle (:func:`stretch`).

* ``aps-reference``: ``aps`` of the pipeline (30 fps, 4 ms exposure, ideal 8-bit frames) on the
  scene's frames, rendered in the run (0.3 s; ``--quick``: 0.1 s); throughput = output frames
  per CPU second of the calling thread spent in ``aps`` (the scene renders on other threads).
  Error = RMS difference, in digital numbers (DN), between each frame and the exposure model
  applied to the exact scene: the mean of :data:`REFERENCE_SAMPLES` renders spread evenly over
  the exposure window (midpoints), times the gain, clipped to the full well, unquantised. Its
  floor is the noise the model adds: the quantisation's 1/sqrt(12) DN for ideal frames
  (``extra``: ``noise_floor_dn``, ``error_over_floor``). ``aps-reference-davis240``: the same
  with ``aps``'s defaults (a DAVIS240C: 25 fps, shot and read noise, 10-bit ADC) on the same
  frames, whose floor adds the expected shot and read noise at each pixel's reference level.
* ``frame-flow-reference``: ``frame_flow`` of the pipeline (OpenCV DIS, one thread, flow over
  100 ms) on the cached ``aps`` frames of the stretch (1 s; ``--quick``: 0.5 s); throughput =
  flow fields (frames with flow) per CPU second; error = AEE (px/s) against the scene's exact
  flow at the flow events (``flow_scorer``'s ``aee_pxs``; relative error and AAE in ``extra``).
* ``foe-lines-reference``: ``foe_lines`` of the pipeline on the cached output of that
  ``frame_flow``; throughput = FOE estimates per CPU second; error = mean |dx| (px) of the
  estimates against the true FOE after :data:`WARMUP_US` (the flow's baseline and the fit's
  window fill then); |dy| and the standard deviations in ``extra``.

The cached inputs (``evchain bench --prepare frame-flow-reference foe-lines-reference``) are
made by :func:`evchain.benchmarks.drive_inputs.drive_aps` and ``drive_flow``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_cpu_time
from evchain.bench_cache import Workload
from evchain.benchmarks.drive_inputs import (
    PIPELINES,
    drive_aps,
    drive_flow,
    load_aps,
    load_flow,
    pipeline_spec,
    relative,
    stretch_label,
)
from evchain.core.filter import Context

PIPELINE = PIPELINES / "frames-reference.yaml"
#: renders averaged over each exposure window for the exposure model's reference frame
REFERENCE_SAMPLES = 32
#: FOE estimates before this time after the stretch's start are not scored, µs
WARMUP_US = 300_000


def stretch(quick: bool) -> tuple[float, float]:
    """(start_m, duration_s) of the flow and FOE rows: 3 s before the obstacle."""
    return (220.0, 0.5) if quick else (220.0, 1.0)


def aps_stretch(quick: bool) -> tuple[float, float]:
    """(start_m, duration_s) of the ``aps`` rows, whose input frames render in the run."""
    return (220.0, 0.1) if quick else (220.0, 0.3)


def _exposure_reference(scene, rate_hz: float, exposure_us: float, t_exposure_start: int,
                        samples: int) -> np.ndarray:
    """The mean of ``samples`` renders at the midpoints of the global-shutter window that
    starts at frame n's start, n from ``t_exposure_start`` (µs)."""
    n = round(t_exposure_start * rate_hz / 1e6)
    start = n * 1e6 / rate_hz
    acc = np.zeros(scene.geometry.shape, np.float64)
    for k in range(samples):
        frame, _ = scene.render((start + (k + 0.5) * exposure_us / samples) * 1e-6)
        acc += frame
    return acc / samples


def _aps_errors(params, frames: np.ndarray, refs: list[np.ndarray]) -> dict:
    """RMS and largest error in DN of ``frames`` against the exposure model on ``refs``, and
    the noise floor the model adds (quantisation, and shot and read noise if on)."""
    levels = (1 << params.adc_bits) - 1
    ref = np.stack(refs)
    electrons = np.clip(ref * params.gain_e_per_unit, 0.0, params.full_well_e)
    err = (frames - electrons / params.full_well_e) * levels
    var_e = (electrons if params.shot_noise else 0.0) + params.read_noise_e ** 2
    floor = math.sqrt(float(np.mean(var_e / params.full_well_e ** 2 * levels ** 2)) + 1 / 12)
    rms = float(np.sqrt(np.mean(err ** 2)))
    return {"rms_dn": rms, "max_dn": float(np.abs(err).max()), "floor_dn": floor}


def aps_rows(pipeline: Path, start_m: float, duration_s: float,
             samples: int = REFERENCE_SAMPLES) -> list[BenchRow]:
    """``aps`` of ``pipeline`` and ``aps`` with its defaults (DAVIS240C) on the frames of
    ``pipeline``'s scene from ``start_m`` for ``duration_s``, rendered in the run."""
    from evchain.filters.aps import Aps

    spec = pipeline_spec(pipeline, start_m, duration_s)
    scene_st, aps_st = spec.stage("scene"), spec.stage("aps")
    variants = {"aps-reference": aps_st.params, "aps-reference-davis240": Aps.Params()}
    ctx = Context(seed=spec.seed)
    source = scene_st.cls()
    source.id = scene_st.id
    source.setup(scene_st.params, ctx)
    stages, outs = {}, {name: [] for name in variants}
    cpu = dict.fromkeys(variants, 0.0)
    for name, params in variants.items():
        f = Aps()
        f.id = aps_st.id
        f.setup(params, ctx)
        stages[name] = f

    def step(name, packet=None):
        c0 = time.thread_time()
        out = stages[name].process(packet) if packet is not None else stages[name].flush()
        cpu[name] += time.thread_time() - c0
        if out is not None:
            outs[name].append(out)

    n_in = 0
    try:
        for packet in source.packets():
            n_in += len(packet.t)
            for name in variants:
                step(name, packet)
        for name in variants:
            step(name)
        rows = []
        for name, params in variants.items():
            frames = np.concatenate([o.frames for o in outs[name]])
            starts = np.concatenate([o.t_exposure_start for o in outs[name]])
            if params.shutter != "global" or not len(frames):
                raise RuntimeError(f"{name}: expected global-shutter frames, got "
                                   f"{len(frames)} {params.shutter} frames")
            refs = [_exposure_reference(source.scene, params.rate_hz, params.exposure_us,
                                        int(s), samples) for s in starts]
            e = _aps_errors(params, frames, refs)
            n_out = len(frames)
            how = ("aps of the pipeline" if name == "aps-reference"
                   else "aps defaults (DAVIS240C: 25 fps, shot and read noise, 10 bit)")
            rows.append(BenchRow(
                name, "aps", n_out / max(cpu[name], 1e-9), "frames/s (CPU)", e["rms_dn"],
                "rms DN vs exposure model", None,
                {"frames": n_out, "input_frames": n_in,
                 "input_frames_per_s": n_in / max(cpu[name], 1e-9),
                 "error_max_dn": e["max_dn"], "noise_floor_dn": e["floor_dn"],
                 "error_over_floor": e["rms_dn"] / e["floor_dn"],
                 "reference_samples": samples, "adc_bits": params.adc_bits,
                 "params": {"aps": params.model_dump(mode="json")}},
                data=f"{stretch_label(scene_st.params.model_dump())}, {n_in} scene frames "
                     f"rendered in the run; {how}",
                params_from=relative(pipeline)))
    finally:
        source.close()
    return rows


def frame_flow_rows(pipeline: Path, start_m: float, duration_s: float,
                    repeat: int = 1) -> list[BenchRow]:
    """``frame_flow`` of ``pipeline`` on the cached ``aps`` frames of the stretch."""
    from evchain.filters.flow_scorer import score_flow

    inp = drive_aps(pipeline, start_m, duration_s)
    packets, ctx = load_aps(inp)
    st = pipeline_spec(pipeline, start_m, duration_s).stage("frame_flow")
    outs: list = []

    def stage():
        f = st.cls()
        f.id = st.id
        f.setup(st.params, Context(geometry=ctx.geometry))
        outs.clear()
        outs.extend(f.process(p) for p in packets)

    cpu = best_cpu_time(stage, repeat=repeat, warmup=True)
    cols = {c: np.concatenate([getattr(o, c) for o in outs]) for c in ("x", "y", "t", "vx",
                                                                       "vy")}
    fields = len(np.unique(cols["t"]))
    n_in = sum(len(p.t) for p in packets)
    score = score_flow(cols["x"], cols["y"], cols["t"], cols["vx"], cols["vy"], ctx.truth)
    return [BenchRow(
        "frame-flow-reference", "frame_flow", fields / cpu, "frames/s (CPU)",
        score["aee_pxs"], "aee_pxs", None,
        {"flow_fields": fields, "input_frames": n_in, "flow_events": len(cols["t"]),
         "flow_events_per_s": len(cols["t"]) / cpu, "ree_pct": score["ree_pct"],
         "aae_deg": score["aae_deg"], "n_scored": score["n_scored"],
         "params": {"frame_flow": st.params.model_dump(mode="json")}},
        data=f"{inp.describe()}; frame_flow of the pipeline",
        params_from=relative(pipeline))]


def foe_lines_rows(pipeline: Path, start_m: float, duration_s: float,
                   repeat: int = 1) -> list[BenchRow]:
    """``foe_lines`` of ``pipeline`` on the cached ``frame_flow`` output of the stretch."""
    inp = drive_flow(pipeline, start_m, duration_s)
    packets, ctx = load_flow(inp)
    st = pipeline_spec(pipeline, start_m, duration_s).stage("foe_lines")
    series: list[np.ndarray] = []

    def stage():
        f = st.cls()
        f.id = st.id
        f.setup(st.params, Context(seed=inp.needs[0].params["seed"], geometry=ctx.geometry))
        series.clear()
        series.extend(f.process(p).series["foe"] for p in packets)

    cpu = best_cpu_time(stage, repeat=repeat, warmup=True)
    s = np.concatenate(series)
    estimates = len(s)
    s = s[s["t"] >= packets[0].t_start + WARMUP_US]
    if not len(s):
        raise RuntimeError(f"foe-lines-reference: no FOE estimate after the warm-up on "
                           f"{inp.describe()}")
    xt, yt = ctx.truth.foe(s["t"].astype(np.float64))
    adx, ady = np.abs(s["x"] - xt), np.abs(s["y"] - yt)
    n_flow = sum(len(p) for p in packets)
    return [BenchRow(
        "foe-lines-reference", "foe_lines", estimates / cpu, "estimates/s (CPU)",
        float(adx.mean()), "foe_dx_mean_px", None,
        {"estimates": estimates, "scored": len(s), "warmup_us": WARMUP_US,
         "flow_events": n_flow, "flow_events_per_s": n_flow / cpu,
         "foe_dx_mean_px": float(adx.mean()), "foe_dx_std_px": float(adx.std()),
         "foe_dy_mean_px": float(ady.mean()), "foe_dy_std_px": float(ady.std()),
         "params": {"foe_lines": st.params.model_dump(mode="json")}},
        data=f"{inp.describe()}; foe_lines of the pipeline",
        params_from=relative(pipeline))]


WORKLOADS = {
    "aps-reference": lambda quick: aps_rows(PIPELINE, *aps_stretch(quick)),
    "frame-flow-reference": Workload(
        lambda quick: frame_flow_rows(PIPELINE, *stretch(quick), repeat=1 if quick else 3),
        lambda quick: [drive_aps(PIPELINE, *stretch(quick))]),
    "foe-lines-reference": Workload(
        lambda quick: foe_lines_rows(PIPELINE, *stretch(quick), repeat=1 if quick else 3),
        lambda quick: [drive_flow(PIPELINE, *stretch(quick))]),
}
