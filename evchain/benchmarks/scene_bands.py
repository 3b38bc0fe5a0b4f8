"""How far the scene's row bands (``band_rows``) move the events from those of frames rendered
whole: the same stretch of a drive through scene -> emulator in both modes, compared.

* ``scene-bands``: bands of 16 rows, one row per stretch (the reference drive's first second
  and its last second before the obstacle, and the evaluation cells ``speed-27`` and
  ``pitch``; quick: 0.25 s of each): throughput = the banded run's simulated s per wall s;
  error = the median |time difference| of matched events (µs); extra:
  :func:`compare_events`'s table and both runs' wall time and rendered share.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow
from evchain.benchmarks.drive_inputs import relative
from evchain.benchmarks.scene_render import BAND_ROWS
from evchain.core.packets import EventPacket

ROOT = Path(__file__).resolve().parents[2]
PIPELINE = ROOT / "pipelines" / "reference.yaml"

#: stretch name -> overrides of pipelines/reference.yaml (the cells of
#: pipelines/sweeps/evaluation.yaml where named so), each 1 s long
STRETCHES = {
    "reference-start": ["scene.start_m=0"],
    "reference-contact": ["scene.start_m=259"],
    "speed-27": ["scene.speed_mps=27", "scene.start_m=158"],
    "pitch": ["scene.dynamics=pitch", "scene.start_m=0"],
}


def compare_events(a: EventPacket, b: EventPacket) -> dict[str, float | int]:
    """Events ``b`` against ``a`` (same geometry): ``n_a``, ``n_b``, ``count_rel_diff`` ((b - a)
    / a), ``pixels_differing`` (share of the pixels with events in either whose per-pixel
    count differs), ``max_pixel_count_diff``, and over the k-th event of each pixel and
    polarity in both (:func:`evchain.report.timing.timing_errors`): ``matched``,
    ``median_abs_dt_us``, ``p95_abs_dt_us``, ``mean_dt_us`` (b - a). Where a pixel's counts
    differ, the k-th events after the first missing one are different crossings, so these
    grow with the stretch's length; :func:`nearest_dt` gives ``nearest_median_abs_dt_us`` and
    ``nearest_p95_abs_dt_us``, which do not."""
    from evchain.report.timing import timing_errors

    w, h = a.geometry.width, a.geometry.height
    ca = np.bincount(a.y.astype(np.int64) * w + a.x, minlength=w * h)
    cb = np.bincount(b.y.astype(np.int64) * w + b.x, minlength=w * h)
    active = (ca > 0) | (cb > 0)
    diff = np.abs(cb - ca)
    truth = np.zeros(len(a), dtype=[("x", np.int64), ("y", np.int64), ("t", np.int64),
                                    ("p", np.int8)])
    truth["x"], truth["y"], truth["t"], truth["p"] = a.x, a.y, a.t, a.p
    te = timing_errors(b.x, b.y, b.p, b.t, truth, w)
    return {
        "n_a": len(a), "n_b": len(b),
        "count_rel_diff": (len(b) - len(a)) / max(len(a), 1),
        "pixels_differing": float((diff[active] > 0).mean()) if active.any() else 0.0,
        "max_pixel_count_diff": int(diff.max()) if len(diff) else 0,
        "matched": te["n_matched"],
        "median_abs_dt_us": te["median_abs_dt_us"],
        "p95_abs_dt_us": te["p95_abs_dt_us"],
        "mean_dt_us": te["mean_dt_us"],
        **nearest_dt(a, b),
    }


def nearest_dt(a: EventPacket, b: EventPacket) -> dict[str, float | int]:
    """Each event of ``b`` against the event of ``a`` nearest in time at the same pixel with
    the same polarity: ``nearest_median_abs_dt_us`` and ``nearest_p95_abs_dt_us`` of |t_b -
    t_a| over the events of ``b`` that have one (``nearest_matched``). A lost or added event
    moves no other event's match; where a pixel fires faster than its events move, a match
    can be a neighbouring crossing (a lower bound then)."""
    w = a.geometry.width
    out = {"nearest_matched": 0, "nearest_median_abs_dt_us": None, "nearest_p95_abs_dt_us": None}
    if not len(a) or not len(b):
        return out
    t0 = min(int(a.t.min()), int(b.t.min()))
    span = max(int(a.t.max()), int(b.t.max())) - t0 + 1

    def keys(e):
        return (e.y.astype(np.int64) * w + e.x) * 2 + (e.p > 0)

    ka, kb = keys(a), keys(b)
    ca = np.sort(ka * span + (a.t.astype(np.int64) - t0))   # by pixel and polarity, then time
    cb = kb * span + (b.t.astype(np.int64) - t0)
    i = np.searchsorted(ca, cb)
    best = np.full(len(b), np.iinfo(np.int64).max)
    for j in (np.minimum(i, len(ca) - 1), np.maximum(i - 1, 0)):   # the neighbours in time
        same = ca[j] // span == kb
        best = np.where(same, np.minimum(best, np.abs(ca[j] - cb)), best)
    dt = best[best < np.iinfo(np.int64).max].astype(np.float64)
    if len(dt):
        out.update(nearest_matched=len(dt), nearest_median_abs_dt_us=float(np.median(dt)),
                   nearest_p95_abs_dt_us=float(np.percentile(dt, 95)))
    return out


def drive_events(overrides: list[str], registry=None) -> tuple[EventPacket, dict]:
    """The events of pipelines/reference.yaml with ``overrides`` (rendered in the run), and
    its wall time and scene metrics."""
    from evchain.core.chain import run_pipeline
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry
    from evchain.io.aedat2 import read_aedat2

    registry = registry or make_registry()
    spec = load_pipeline(PIPELINE, registry, overrides)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        result = run_pipeline(spec, registry, Path(tmp) / "run")
        wall = time.perf_counter() - t0
        events = read_aedat2(Path(tmp) / "run" / "events.aedat")
    scene = result.report["metrics"]["scene"]
    return events, {"wall_s": wall, "simulated_s": scene["duration_s"],
                    "frames": scene["frames"],
                    "rendered_share": scene.get("rendered_share", 1.0)}


def agreement(overrides: list[str], band_rows: int, registry=None) -> dict:
    """Both modes on one stretch: the whole-frame run, the banded one and their comparison."""
    whole, run_a = drive_events([*overrides, "scene.band_rows=0"], registry)
    banded, run_b = drive_events([*overrides, f"scene.band_rows={band_rows}"], registry)
    return {**compare_events(whole, banded), "whole": run_a, "banded": run_b}


def scene_bands(quick: bool) -> list[BenchRow]:
    from evchain.core.registry import make_registry

    registry = make_registry()
    duration = 0.25 if quick else 1.0
    band_rows = BAND_ROWS
    drive_events(["scene.duration_s=0.002"], registry)          # compile
    rows = []
    for name, overrides in STRETCHES.items():
        res = agreement([*overrides, f"scene.duration_s={duration:g}"], band_rows, registry)
        banded = res.pop("banded")
        whole = res.pop("whole")
        rows.append(BenchRow(
            f"scene-bands-{name}", "scene+emulator",
            banded["simulated_s"] / banded["wall_s"], "sim s/s",
            error=res["median_abs_dt_us"], error_name="median |dt| of matched events (µs)",
            extra={**res, "band_rows": band_rows,
                   "rendered_share": banded["rendered_share"],
                   "whole_sim_s_per_s": whole["simulated_s"] / whole["wall_s"]},
            data=f"{name}: reference.yaml {' '.join(overrides)}, {duration:g} s, banded "
                 "against whole frames",
            params_from=relative(PIPELINE)))
    return rows


WORKLOADS = {"scene-bands": scene_bands}
