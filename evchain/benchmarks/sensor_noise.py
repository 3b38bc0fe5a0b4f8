"""Benchmark of ``sensor_noise``: row ``sensor-noise-reference``.

The emulator's events of the reference drive's last 5 s before the obstacle (``--quick``: 1 s
at 220 m), the cached input of the ``chain-reference-lk`` rows (pipelines/reference.yaml's
``scene`` and ``emulator``, whose ``sensor_noise`` is off), through ``sensor_noise`` with the
evaluation's noise cells together (:data:`NOISE`: leak events at 0.1 Hz per pixel, 0.1 % hot
pixels at 1 kHz) and shot noise at 1 Hz per pixel (dim light). Throughput = input events per
CPU second of ``process`` over the emulator's packets (the machine may be shared; wall time in
``extra``); ``limit_ratio`` = CPU time of copying the output's columns once / the stage's.

The noise is what the output has beyond the input, counted per pixel (the stage only adds
events; a pixel with fewer events out than in stops the row). Hot pixels are the pixels with at
least half the configured hot-pixel count; the others' mean noise rate is the measured
background activity. Error = |measured / configured background activity - 1| (configured:
``leak_rate_hz + shot_rate_hz``); ``extra``: the measured and configured shares of hot pixels,
whether they are exactly the pixels the stage chose, their rate, the share of ON events in the
background activity against the configured one, and the sampling spread of the measured rate
(the shot noise's Poisson count; the leak is nearly regular).
"""

from __future__ import annotations

import math

import numpy as np

from evchain.bench import BenchRow, best_cpu_time, best_time
from evchain.bench_cache import BenchInput, Workload
from evchain.benchmarks.drive_inputs import PIPELINES, drive_events, load_events, relative
from evchain.benchmarks.foe_ttc import stretch
from evchain.core.filter import Context

PIPELINE = PIPELINES / "reference.yaml"
#: the evaluation's noise cells (noise-ba-0.1hz, noise-hot-0.1pct) and dim-light shot noise
NOISE = {"leak_rate_hz": 0.1, "shot_rate_hz": 1.0, "hot_pixel_fraction": 0.001,
         "hot_pixel_rate_hz": 1000.0}


def events_input(quick: bool) -> BenchInput:
    return drive_events(PIPELINE, *stretch(quick))


def _counts(packets, npix: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(events, ON events) per pixel (flat index y * width + x) of ``packets``."""
    flat = np.concatenate([p.y.astype(np.int64) * width + p.x for p in packets])
    on = np.concatenate([p.p > 0 for p in packets])
    return np.bincount(flat, minlength=npix), np.bincount(flat[on], minlength=npix)


def noise_rows(inp: BenchInput, repeat: int = 3, noise: dict | None = None) -> list[BenchRow]:
    """``sensor_noise`` with ``noise`` (default :data:`NOISE`) on the events of ``inp``."""
    from evchain.filters.sensor_noise import SensorNoise

    noise = dict(NOISE if noise is None else noise)
    packets, ctx = load_events(inp)
    g = ctx.geometry
    npix = g.width * g.height
    params = SensorNoise.Params(**noise)
    outs: list = []
    made: list = []

    def stage():
        f = SensorNoise()
        f.id = "sensor_noise"
        f.setup(params, Context(seed=inp.params["seed"], geometry=g))
        outs.clear()
        outs.extend(f.process(p) for p in packets)
        made[:] = [f]

    cpu = best_cpu_time(stage, repeat=repeat, warmup=True)
    wall = best_time(stage, repeat=1)
    n_in = sum(len(p) for p in packets)
    n_out = sum(len(p) for p in outs)
    cpu_limit = best_cpu_time(lambda: [np.concatenate([getattr(o, c) for o in outs])
                                       for c in ("x", "y", "t", "p")], repeat=repeat)

    seconds = (packets[-1].t_end - packets[0].t_start) * 1e-6
    count_in, on_in = _counts(packets, npix, g.width)
    count_out, on_out = _counts(outs, npix, g.width)
    added, added_on = count_out - count_in, on_out - on_in
    if np.any(added < 0) or np.any(added_on < 0):
        raise RuntimeError("sensor-noise-reference: the stage dropped input events")
    hot = added >= 0.5 * noise["hot_pixel_rate_hz"] * seconds
    chosen = np.zeros(npix, bool)
    chosen[made[0].hot_pixels] = True
    ba = ~hot
    ba_rate = float(added[ba].sum()) / (int(ba.sum()) * seconds)
    want_ba = noise["leak_rate_hz"] + noise["shot_rate_hz"]
    error = abs(ba_rate / want_ba - 1) if want_ba else None
    shot_count = noise["shot_rate_hz"] * int(ba.sum()) * seconds
    on_share = float(added_on[ba].sum()) / max(float(added[ba].sum()), 1.0)
    return [BenchRow(
        "sensor-noise-reference", "sensor_noise", n_in / cpu, "events/s (CPU)", error,
        "BA rate rel. error", cpu_limit / cpu,
        {"events": n_in, "noise_events": n_out - n_in, "throughput_wall_eps": n_in / wall,
         "seconds": seconds, "ba_rate_hz": ba_rate, "ba_rate_configured_hz": want_ba,
         "ba_rate_sampling_rel_sd": (math.sqrt(shot_count) / (want_ba * int(ba.sum()) * seconds)
                                     if want_ba else None),
         "hot_pixel_share": float(hot.mean()),
         "hot_pixel_share_configured": round(noise["hot_pixel_fraction"] * npix) / npix,
         "hot_pixels_as_chosen": bool(np.array_equal(hot, chosen)),
         "hot_pixel_rate_hz": (float(added[hot].sum()) / (int(hot.sum()) * seconds)
                               if hot.any() else None),
         "ba_on_share": on_share,
         "ba_on_share_configured": ((noise["leak_rate_hz"] + noise["shot_rate_hz"] / 2)
                                    / want_ba if want_ba else None),
         "params": {"sensor_noise": params.model_dump(mode="json")}},
        data=(f"{inp.describe()}; leak {noise['leak_rate_hz']:g} Hz, shot "
              f"{noise['shot_rate_hz']:g} Hz, {noise['hot_pixel_fraction'] * 100:g} % hot "
              f"pixels at {noise['hot_pixel_rate_hz']:g} Hz"),
        params_from=relative(PIPELINE))]


WORKLOADS = {"sensor-noise-reference": Workload(
    lambda quick: noise_rows(events_input(quick), repeat=1 if quick else 3),
    lambda quick: [events_input(quick)])}
