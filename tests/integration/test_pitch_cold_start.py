"""A gear shift within foe_fit's cold start, on a rendered drive (the tuning pitch drive of
layout seed 4, pipelines/sweeps/tuning-pitch.yaml, its first 1.2 s): the shift at 0.5 s comes
before the fits may change mode (3 ``tau_ms`` after the cold start), the level fit runs far
from foe_map's votes, which the pitch pulls up, and the votes' fit explains more than it. A
pitching fit from scratch explains more still: the fits pitch from there, and the FOE's row
does not jump to the votes' row 20 px off at the shift's second swing (1.0 s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evchain.core.chain import run_pipeline
from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry
from evchain.filters.scene_events import replay_spec

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
DRIVE = ["scene.dynamics=pitch", "scene.start_m=180", "scene.layout_seed=4",
         "scene.duration_s=1.2"]


def test_a_gear_shift_in_the_cold_start_is_fitted_as_pitch(tmp_path):
    registry = make_registry()
    run_pipeline(load_pipeline(PIPELINES / "reference.yaml", registry, DRIVE), registry,
                 tmp_path / "record")
    spec = load_pipeline(PIPELINES / "reference-lk.yaml", registry,
                         [*DRIVE, "foe_ttc_scorer.plots=false"])
    run_pipeline(replay_spec(spec, tmp_path / "record" / "events.aedat"), registry,
                 tmp_path / "lk")
    fe = np.genfromtxt(tmp_path / "lk" / "series" / "foe_error.csv", delimiter=",",
                       names=True)
    shift = (fe["t"] >= 550_000) & (fe["t"] < 1_100_000)
    assert np.mean(fe["wx_deg_s"][shift] != 0) > 0.8   # the fits pitch through the shift
    assert np.abs(fe["dy"][shift]).max() < 10.0         # the row stays with the heading
