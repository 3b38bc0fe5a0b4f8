"""Benchmarks of the driving-scene simulator.

* ``scene-render``: frames/s rendering the high-rise reference view (320x240, 2x2 supersampling)
  on one core, at times spread over the drive; the error column is the largest difference of a
  small frame against the slow numpy reference of tests/naive (0 up to rounding). Extra:
  ``cpu_frames_per_s`` from the thread's CPU time (the machine may be shared).
  ``scene-render-2threads``: the same with rows on two threads (CPU rate and CPU ns per ray
  of the whole process).
* ``reference-drive``: pipelines/reference.yaml (scene -> emulator -> aedat_writer, its
  parameters) over the whole 14 s drive (quick: the first 1 s), rendered in the run, as
  simulated seconds per wall second; reports the event rate next to the thesis's 259 k events/s.
  ``reference-drive-bands``: the same with row bands (``band_rows: 16``; the pipeline renders
  every frame whole), measured in the same run.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow
from evchain.benchmarks.drive_inputs import relative

PIPELINE = Path(__file__).resolve().parents[2] / "pipelines" / "reference.yaml"


def _naive_error() -> float | None:
    import sys

    root = Path(__file__).resolve().parents[2]
    if not (root / "tests" / "naive" / "scene_kernels.py").exists():
        return None          # installed without the tests folder
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    from evchain.sim.drive import Scene
    from tests.naive import scene_kernels as naive

    sc = Scene.from_params(scenario="high-rise", width=16, height=12, start_m=150.0)
    return float(np.abs(sc.render(0.7)[0] - naive.render(sc, 0.7)).max())


def _render_rate(threads: int, n: int) -> tuple[float, float]:
    """(wall frames/s, CPU-time frames/s) over n frames spread over the reference drive."""
    from evchain.sim.drive import Scene

    sc = Scene.from_params(threads=threads, scenario="high-rise", width=320, height=240,
                           supersample=2)
    times = np.linspace(0.0, sc.duration_s * 0.98, n)
    out = np.empty((240, 320), np.float32)
    sc.render(0.0, out)                        # compile / warm up
    clock = time.thread_time if threads == 1 else time.process_time
    w0, c0 = time.perf_counter(), clock()
    for t in times:
        sc.render(float(t), out)
    return n / (time.perf_counter() - w0), n / (clock() - c0)


def scene_render(quick: bool) -> list[BenchRow]:
    n = 8 if quick else 40
    err = _naive_error()
    rows = []
    for threads, name in ((1, "scene-render"), (2, "scene-render-2threads")):
        wall, cpu = _render_rate(threads, n)
        rows.append(BenchRow(name, "scene", wall, "frames/s", error=err,
                             error_name="max |frame - numpy ref|",
                             extra={"threads": threads, "cpu_frames_per_s": cpu,
                                    "cpu_ns_per_ray": 1e9 / (cpu * 320 * 240 * 4),
                                    "frames": n, "goal_frames_per_s": 300},
                             data=f"high-rise view 320x240, 2x2 supersampling, {n} frames"))
    return rows


def _drive_row(name: str, overrides: list[str], registry) -> BenchRow:
    """One run of pipelines/reference.yaml with ``overrides``, timed (compiled beforehand)."""
    from evchain.core.chain import run_pipeline
    from evchain.core.config import load_pipeline

    spec = load_pipeline(PIPELINE, registry, overrides)
    have_emulator = any(s.use == "emulator" for s in spec.stages)
    with tempfile.TemporaryDirectory() as tmp:
        # compile outside the timing: a few frames through the same chain
        warm = load_pipeline(PIPELINE, registry, [*overrides, "scene.duration_s=0.002"])
        run_pipeline(warm, registry, Path(tmp) / "warm")
        t0 = time.perf_counter()
        result = run_pipeline(spec, registry, Path(tmp) / "run")
        wall = time.perf_counter() - t0
    rep = result.report
    scene = rep["metrics"]["scene"]
    sim_s = scene["duration_s"]
    stages = {s["name"]: s for s in rep["filters"]}
    events = stages["emulator"]["events_out"] if have_emulator else 0
    extra = {"simulated_s": sim_s, "wall_s": wall, "frames": scene["frames"],
             "rendered_share": scene.get("rendered_share", 1.0),
             "band_rows": spec.stages[0].params.band_rows,
             "events": events, "event_rate_eps": events / sim_s,
             "thesis_event_rate_eps": 259_000,
             "scene_wall_s": stages["scene"]["wall_s"],
             "emulator_wall_s": stages.get("emulator", {}).get("wall_s")}
    return BenchRow(name, "scene+emulator", sim_s / wall, "sim s/s",
                    error=events / sim_s, error_name="event rate (events/s)", extra=extra,
                    data=f"reference drive 0-{sim_s:g} s, rendered in the run"
                         + (f", bands of {BAND_ROWS} rows" if "bands" in name else ""),
                    params_from=relative(PIPELINE))


#: rows per band of the banded rows (``reference-drive-bands``, ``scene-bands``)
BAND_ROWS = 16


def reference_drive(quick: bool) -> list[BenchRow]:
    """The drive as the pipeline sets it (every frame rendered whole), then with row bands
    (``band_rows`` :data:`BAND_ROWS`), in one run so that both see the same load."""
    from evchain.core.registry import make_registry

    registry = make_registry()
    base = ["scene.duration_s=1.0"] if quick else []
    return [_drive_row("reference-drive", base, registry),
            _drive_row("reference-drive-bands", [*base, f"scene.band_rows={BAND_ROWS}"],
                       registry)]


WORKLOADS = {"scene-render": scene_render, "reference-drive": reference_drive}
