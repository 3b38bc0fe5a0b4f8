"""The golden stretches of the reference drive, each rendered once and run through both chains.

Two stretches of 2 s (40 m at 20 m/s), the last 80 m of the street in two halves: ``cruise``
from 200 m, where the FOE is scored (the obstacle is still far), and ``approach``, the drive's
last 2 s, where the TTC is scored (the obstacle emerges and comes close; the FOE is dragged by
it there and is not what this stretch guards). An FOE averaged over 1.5 s depends on exactly
where frames and events fall: started 10 or 20 ms earlier, its mean |dx| moves by up to a few
pixels on some stretches. So every stretch runs three times, started 0, 0.2 and 0.4 m earlier,
and the median of the three is what is guarded.
Shared by the golden tests (tests/golden/test_golden.py) and the script that changes their
expected values (tests/golden/update.py), so both measure exactly the same thing.
"""

from __future__ import annotations

import statistics
from pathlib import Path

from evchain.core.chain import run_pipeline
from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry
from evchain.filters.scene_events import replay_spec

ROOT = Path(__file__).resolve().parents[2]
PIPELINES = ROOT / "pipelines"
EXPECTED = Path(__file__).resolve().parent / "expected.json"
#: where each stretch starts on the 280 m street (m) and what it guards (metrics of report.json)
STRETCHES = {
    "cruise": (200.0, ("foe.dx_mean_px", "foe.dy_mean_px", "flow.invalid_rate",
                       "flow.density")),
    "approach": (240.0, ("ttc.share_on_obstacle_within_20pct", "ttc.coverage_on_obstacle",
                         "ttc.median_rel_error_on_obstacle", "ttc.median_rel_error_last3s")),
}
DURATION_S = 2.0
#: the three starts of every stretch, relative to its start (m)
SHIFTS_M = (0.0, -0.2, -0.4)
#: the FOE's warm-up is a quarter of the stretch; no pictures
SCORING = ["foe_ttc_scorer.warmup_s=0.5", "foe_ttc_scorer.plots=false"]
FLOWS = {"lk": "reference-lk.yaml", "plane": "reference-plane.yaml"}


def overrides(stretch: str, shift_m: float = 0.0) -> list[str]:
    start = STRETCHES[stretch][0] + shift_m
    return [f"scene.start_m={start:g}", f"scene.duration_s={DURATION_S:g}"]


def record(stretch: str, out: Path, shift_m: float = 0.0) -> Path:
    """Render and emulate a stretch with pipelines/reference.yaml, started ``shift_m`` later
    (negative: earlier); the events file."""
    registry = make_registry()
    spec = load_pipeline(PIPELINES / "reference.yaml", registry, overrides(stretch, shift_m))
    run_pipeline(spec, registry, out / stretch / "record")
    return out / stretch / "record" / "events.aedat"


def run_flow(stretch: str, flow: str, events: Path, out: Path,
             shift_m: float = 0.0) -> dict[str, float | None]:
    """Replay a recorded stretch through pipelines/reference-<flow>.yaml; the metrics it
    guards."""
    registry = make_registry()
    spec = load_pipeline(PIPELINES / FLOWS[flow], registry,
                         overrides(stretch, shift_m) + SCORING)
    report = run_pipeline(replay_spec(spec, events), registry, out / stretch / flow).report
    got = {}
    for key in STRETCHES[stretch][1]:
        group, name = key.split(".", 1)
        got[key] = report["metrics"].get(group, {}).get(name)
    return got


def record_all(out: Path) -> dict[tuple[str, float], Path]:
    """Every stretch at every shift: {(stretch, shift): events file}."""
    return {(name, shift): record(name, out / f"shift{shift:g}", shift)
            for name in STRETCHES for shift in SHIFTS_M}


def medians(name: str, flow: str, events: dict[tuple[str, float], Path],
            out: Path) -> tuple[dict[str, float | None], dict[str, list[float | None]]]:
    """(median over the shifts, the runs' values) of each metric a stretch guards."""
    runs = [run_flow(name, flow, events[(name, shift)], out / f"shift{shift:g}", shift)
            for shift in SHIFTS_M]
    values = {key: [r[key] for r in runs] for key in STRETCHES[name][1]}
    return {k: (None if None in v else statistics.median(v)) for k, v in values.items()}, values
