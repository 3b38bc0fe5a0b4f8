"""The reference chains on hard cases, each on a small, short drive (80x60, no supersampling):
very slow and very fast driving, a uniform grey scene with and without sensor noise, extreme
emulator thresholds, the curves route without an obstacle, the last moments before contact.
Whatever they meet: no exception, no NaN or infinity in any series or metric, no TTC below
what the bounds allow, and where there is no estimate, a reason."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry
from evchain.filters.scene_events import replay_spec

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
SMALL = ["scene.width=80", "scene.height=60", "scene.supersample=1"]
FLOWS = ("lk", "plane")
#: the noise of the evaluation's noise cells, stronger: 1 Hz leak and shot noise per pixel,
#: 0.5 % hot pixels at 1 kHz
NOISE = ["sensor_noise.leak_rate_hz=1", "sensor_noise.shot_rate_hz=1",
         "sensor_noise.hot_pixel_fraction=0.005", "sensor_noise.hot_pixel_rate_hz=1000"]
#: name: (scene and emulator overrides, recording-only overrides)
CASES = {
    "grey": (["scene.contrast=0", "scene.start_m=250", "scene.duration_s=1.5"], []),
    "grey-noise": (["scene.contrast=0", "scene.start_m=250", "scene.duration_s=1.5"], NOISE),
    "speed-1": (["scene.speed_mps=1", "scene.start_m=277", "scene.duration_s=3"], []),
    "speed-40": (["scene.speed_mps=40", "scene.start_m=220", "scene.duration_s=1.5"], []),
    "threshold-0.05": (["emulator.log_mapping=natural", "emulator.threshold_on=0.05",
                        "emulator.threshold_off=0.05", "scene.start_m=255",
                        "scene.duration_s=1.25"], []),
    "threshold-2": (["emulator.log_mapping=natural", "emulator.threshold_on=2.0",
                     "emulator.threshold_off=2.0", "scene.start_m=250",
                     "scene.duration_s=1.5"], []),
    "curves": (["scene.scenario=curves", "scene.dynamics=curves", "scene.start_m=95",
                "scene.duration_s=1.5"], []),
    # the car 0.1 m past the route's end: the drive ends 5 ms before contact
    "contact": (["scene.start_m=274", "scene.obstacle_gap_m=0.1", "scene.duration_s=0.3"], []),
}


def _no_nan_constant(name):
    raise AssertionError(f"report.json holds {name}")


@pytest.fixture(scope="module", params=list(CASES))
def case(request, tmp_path_factory):
    """A case recorded once and replayed through both reference chains: (name, {flow:
    (report, {series: array})})."""
    name = request.param
    sets, record_only = CASES[name]
    registry = make_registry()
    out = tmp_path_factory.mktemp(name)
    spec = load_pipeline(PIPELINES / "reference.yaml", registry, SMALL + sets + record_only)
    run_pipeline(spec, registry, out / "record")
    runs = {}
    for flow in FLOWS:
        spec = load_pipeline(PIPELINES / f"reference-{flow}.yaml", registry,
                             SMALL + sets + ["foe_ttc_scorer.plots=false"])
        run_pipeline(replay_spec(spec, out / "record" / "events.aedat"), registry, out / flow)
        report = json.loads((out / flow / "report.json").read_text(),
                            parse_constant=_no_nan_constant)
        text = {p.stem: p.read_text() for p in (out / flow / "series").glob("*.csv")}
        series = {k: np.atleast_1d(np.genfromtxt((out / flow / "series" / f"{k}.csv"),
                                                 delimiter=",", names=True))
                  for k, v in text.items() if v.count("\n") > 1}
        for k, v in text.items():
            assert "nan" not in v.lower() and "inf" not in v.lower(), (name, flow, k)
        runs[flow] = (report, series)
    return name, runs


def _numbers(value):
    if isinstance(value, dict):
        for v in value.values():
            yield from _numbers(v)
    elif isinstance(value, list):
        for v in value:
            yield from _numbers(v)
    elif isinstance(value, float):
        yield value


def test_runs_and_every_number_is_finite(case):
    name, runs = case
    for flow, (report, _) in runs.items():
        assert report["status"] == "ok", (name, flow, report["error"])
        assert all(math.isfinite(v) for v in _numbers(report["metrics"])), (name, flow)
        for group in ("foe", "ttc", "foe_map", "foe_fit", "ttc_filter"):
            assert group in report["metrics"], (name, flow, group)


def test_no_ttc_below_the_bounds(case):
    """Every TTC reported is at least ttc's min_tau_s (0.02 s) and implies an image speed at
    its cluster (distance from the FOE over tau) of at most max_speed_pxs."""
    name, runs = case
    for flow, (_, series) in runs.items():
        ttc, foe = series.get("ttc"), series.get("foe")
        if ttc is None:
            continue
        assert ttc["tau_s"].min() >= 0.02, (name, flow)
        j = np.searchsorted(foe["t"], ttc["t"], side="right") - 1
        assert (j >= 0).all()
        d = np.hypot(ttc["x"] - foe["x"][j], ttc["y"] - foe["y"][j])
        assert (d / ttc["tau_s"] <= 20_000).all(), (name, flow)


def test_metrics_that_are_none_say_why(case):
    name, runs = case
    for flow, (report, _) in runs.items():
        for group in ("foe", "ttc", "flow"):
            m = report["metrics"][group]
            empty = [k for k, v in m.items() if v is None and k not in ("lag_ms", "lag_axis")]
            if empty:
                why = m.get("why_none")
                assert why, (name, flow, group, empty)
                if isinstance(why, dict):
                    on_obstacle = {"share_on_obstacle_within_20pct", "coverage_on_obstacle"}
                    assert set(empty) - on_obstacle <= set(why), (name, flow, group, empty)


def test_short_windows_are_reported(case):
    """Every case is shorter than the scorer's 3 s TTC window (or has no true TTC): the window
    used is in the metrics and a warning says it is short."""
    name, runs = case
    for report, _ in runs.values():
        t = report["metrics"]["ttc"]
        if t.get("n") == 0:     # no obstacle: nothing scored
            assert name == "curves" and "no obstacle ahead" in t["why_none"]
            continue
        assert t["window_s"] < 3.0
        assert any("shorter than last_window_s 3 s" in w for w in report["warnings"])
        # the FOE is scored after its 1 s warm-up, to the stream's end (a replay runs from
        # the first event to the last)
        want = max(0.0, float(CASES[name][0][-1].split("=")[1]) - 1.0)
        assert want - 0.1 <= report["metrics"]["foe"]["window_s"] <= want + 1e-9


def test_case_specific_outcomes(case):
    name, runs = case
    for report, series in runs.values():
        m = report["metrics"]
        if name == "grey":      # no event at all: nothing anywhere, and why
            assert "foe" not in series and "ttc" not in series
            assert m["foe_map"]["no_estimate"]["no votes yet"] == m["foe_map"]["reads"] > 0
            assert m["ttc_filter"]["no_estimate"]["no FOE yet"] == m["ttc_filter"]["ticks"]
            assert m["foe"]["why_none"].startswith("no FOE estimate")
        elif name == "grey-noise":  # noise alone: its flow votes, but gives no FOE
            assert "foe" not in series and "ttc" not in series
            fm = m["foe_map"]
            assert fm["estimates"] == 0 and fm["no_estimate"]["consensus at noise level"] > 0
            assert m["ttc"]["coverage_last3s"] == 0.0
        elif name == "curves":  # no obstacle: TTCs are not scored, the series holds no NaN
            err = series["ttc_error"]
            assert (err["tau_true_s"] == -1).all() and (err["rel_error"] == -1).all()
        else:                   # a drive towards the car: the chain estimates
            assert "foe" in series and m["foe_map"]["estimates"] > 0
