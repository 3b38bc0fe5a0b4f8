"""How the scene's time sampling sets the events' timing: ``scene-sampling``.

The emulator interpolates each pixel's intensity between frames, and a frame is due when the
fastest sample has moved ``max_motion_px`` (with ``band_rows``, each band when its own fastest
sample has). Coarser sampling renders less and moves the events. Each row runs a 1 s stretch of
pipelines/reference.yaml (scene -> emulator, rendered in the run) with one sampling and
compares its events with those of the same stretch rendered four times as finely as the
pipeline (``max_motion_px`` 0.125, whole frames), which stands in for the continuous scene:

* throughput: simulated s per wall s of the run (set-up included; the pipeline renders on
  all cores);
* error: the median |time difference| of each event to the fine render's event nearest in time
  at its pixel with its polarity (µs; :func:`evchain.benchmarks.scene_bands.nearest_dt`);
* extra: that comparison's other fields, the frames and the share of rows rendered.

The fine render is not the continuous scene either: its own error is not measured, so the
errors are those relative to it (a lower bound of each sampling's own).
"""

from __future__ import annotations

from evchain.bench import BenchRow
from evchain.benchmarks.drive_inputs import relative
from evchain.benchmarks.scene_bands import PIPELINE, STRETCHES, compare_events, drive_events

#: the reference of every comparison: a quarter of the pipeline's max_motion_px, whole frames
FINE_MOTION_PX = 0.125
#: (max_motion_px, band_rows) of the rows: the pipeline's (0.5, whole frames) among them
SAMPLINGS = ((0.25, 0), (0.5, 0), (0.5, 16), (1.0, 0), (1.0, 16))
#: the stretches of ``scene-bands`` measured here: the reference drive's first and last second,
#: and the pitching camera
NAMES = ("reference-start", "reference-contact", "pitch")


def _sampling(motion_px: float, band_rows: int) -> list[str]:
    return [f"scene.max_motion_px={motion_px:g}", f"scene.band_rows={band_rows}"]


def scene_sampling(quick: bool) -> list[BenchRow]:
    from evchain.core.registry import make_registry

    registry = make_registry()
    duration = 0.25 if quick else 1.0
    drive_events(["scene.duration_s=0.002"], registry)          # compile
    rows = []
    for name in NAMES:
        stretch = [*STRETCHES[name], f"scene.duration_s={duration:g}"]
        fine, fine_run = drive_events([*stretch, *_sampling(FINE_MOTION_PX, 0)], registry)
        for motion_px, band_rows in SAMPLINGS:
            events, run = drive_events([*stretch, *_sampling(motion_px, band_rows)], registry)
            res = compare_events(fine, events)
            bands = f", bands of {band_rows} rows" if band_rows else ""
            rows.append(BenchRow(
                f"scene-sampling-{name}-{motion_px:g}px" + (f"-bands{band_rows}" if band_rows
                                                          else ""),
                "scene+emulator", run["simulated_s"] / run["wall_s"], "sim s/s",
                error=res["nearest_median_abs_dt_us"],
                error_name="median |dt| to a 4x finer render (µs)",
                extra={**res, "max_motion_px": motion_px, "band_rows": band_rows,
                       "frames": run["frames"], "rendered_share": run["rendered_share"],
                       "fine_frames": fine_run["frames"]},
                data=f"{name}: reference.yaml {' '.join(STRETCHES[name])}, {duration:g} s, "
                     f"max_motion_px {motion_px:g}{bands}, against max_motion_px "
                     f"{FINE_MOTION_PX:g}",
                params_from=relative(PIPELINE)))
    return rows


WORKLOADS = {"scene-sampling": scene_sampling}
