"""The reference chains on a recording with every kind of sensor noise: they run, and every
metric they report is a number (no NaN)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry
from evchain.filters.scene_events import replay_spec

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
#: a short, small stretch close to the obstacle
SCENE = ["scene.width=80", "scene.height=60", "scene.supersample=1", "scene.start_m=250",
         "scene.duration_s=1.5"]
NOISE = ["sensor_noise.leak_rate_hz=1", "sensor_noise.shot_rate_hz=1",
         "sensor_noise.hot_pixel_fraction=0.005", "sensor_noise.hot_pixel_rate_hz=1000"]


@pytest.fixture(scope="module")
def noisy_recording(tmp_path_factory) -> Path:
    registry = make_registry()
    out = tmp_path_factory.mktemp("noisy") / "record"
    spec = load_pipeline(PIPELINES / "reference.yaml", registry, SCENE + NOISE + ["seed=3"])
    report = run_pipeline(spec, registry, out, progress=False).report
    counts = {f["id"]: f for f in report["filters"]}
    noise = counts["sensor_noise"]
    # 24 hot pixels at 1 kHz for 1.5 s alone add 36 000 events
    assert noise["events_out"] - noise["events_in"] > 30_000
    return out / "events.aedat"


def _numbers(metrics: dict) -> list[tuple[str, float]]:
    return [(f"{g}.{k}", v) for g, group in metrics.items() if isinstance(group, dict)
            for k, v in group.items() if isinstance(v, float)]


@pytest.mark.parametrize("flow", ["reference-lk.yaml", "reference-plane.yaml"])
def test_reference_chain_runs_on_noisy_events(flow, noisy_recording, tmp_path):
    registry = make_registry()
    spec = load_pipeline(PIPELINES / flow, registry, SCENE + ["seed=3"])
    report = run_pipeline(replay_spec(spec, noisy_recording), registry, tmp_path,
                          progress=False).report
    assert report["status"] == "ok"
    numbers = _numbers(report["metrics"])
    assert any(k.startswith("flow.") for k, _ in numbers)
    assert any(k.startswith("foe.") for k, _ in numbers)
    assert [k for k, v in numbers if math.isnan(v)] == []
