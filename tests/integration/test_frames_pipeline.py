"""The frame baseline's pipeline runs end to end on a short, small stretch of the drive."""

from __future__ import annotations

from pathlib import Path

import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry

pytest.importorskip("cv2")

PIPELINE = Path(__file__).resolve().parents[2] / "pipelines" / "frames-reference.yaml"


def test_frames_reference_runs(tmp_path):
    registry = make_registry()
    spec = load_pipeline(PIPELINE, registry, [
        "scene.width=96", "scene.height=72", "scene.supersample=1", "scene.start_m=250",
        "scene.duration_s=0.6", "scene.threads=1", "aps.rate_hz=100",
        "foe_ttc_scorer.warmup_s=0.2", "foe_ttc_scorer.plots=false"])
    rep = run_pipeline(spec, registry, tmp_path).report
    assert rep["status"] == "ok"
    names = [f["name"] for f in rep["filters"]]
    assert names == ["scene", "aps", "frame_flow", "flow_scorer", "foe_lines", "ttc",
                     "foe_ttc_scorer"]
    aps = rep["filters"][1]
    assert aps["unit_in"] == "frames" and 55 <= aps["events_out"] <= 60   # 100 fps for 0.6 s
    assert rep["filters"][2]["events_out"] > 0
    assert rep["cpu"]["after"] == "aps"
    assert rep["cpu"]["stages"] == ["frame_flow", "foe_lines", "ttc"]
    assert rep["metrics"]["foe"]["n"] > 0 and rep["metrics"]["flow"]["n_flow"] > 0
