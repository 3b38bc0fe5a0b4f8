"""Benchmarks of the DVS emulator: ``emulator-sparse`` (a smooth random texture translating at
20 px/s) and ``emulator-bar`` / ``emulator-bar-linear`` (a bar crossing the view at 200 px/s,
error = spike timing against the analytic crossing times), both 320x240, made in the run.

Throughput is measured through the filter (``process`` on packets of 100 frames, then
``flush``), best CPU time (``time.process_time``) of a few runs, one thread: the machine is
shared, so wall time would count other processes' turns. ``limit_ratio`` = CPU time of one
numpy copy of the same frames into a preallocated buffer / emulator CPU time (1.0 = as fast as
touching the frames once).
"""

from __future__ import annotations

import time

import numpy as np

from evchain.bench import BenchRow, best_cpu_time

W, H = 320, 240


def _run(frames, times, params, record=False):
    """The output packets and, if ``record``, the float times; without ``record`` only the
    event count (timed runs): each packet is dropped once counted, as a streaming pipeline
    passes it on. Holding all of them (or joining them) makes every packet land in fresh
    memory, whose page faults (~2.7 µs per 4 KiB here) are the benchmark's cost, not the
    emulator's."""
    from evchain.core.filter import Context
    from evchain.core.packets import FramePacket, Geometry
    from evchain.filters.emulator import Emulator

    g = Geometry(W, H)
    f = Emulator()
    f.record_float_times = record
    f.setup(Emulator.Params(**params), Context(seed=0))
    outs = []
    count = 0
    n = len(times)
    for i in range(0, n, 100):
        j = min(i + 100, n)
        t_end = int(times[j]) if j < n else int(times[-1]) + 1
        out = f.process(FramePacket(geometry=g, t_start=int(times[i]), t_end=t_end,
                                    frames=frames[i:j], t=times[i:j]))
        count += len(out)
        if record:
            outs.append(out)
    out = f.flush()
    count += len(out)
    if not record:
        return count
    outs.append(out)
    return outs, np.concatenate(f.float_times)


def _copy_time(frames) -> float:
    """CPU time of one copy of the frames (same float32 array the emulator reads) into a
    buffer allocated once: a fresh ``frames.copy()`` would also count page faults on a new
    output of the frames' size (~25 % more here), which the emulator never allocates."""
    out = np.empty_like(frames)
    return best_cpu_time(lambda: np.copyto(out, frames), repeat=3, warmup=True)


def textured_scene(n: int, speed_pxs: float = 20.0, dt_us: int = 1000):
    """A smooth random texture (sum of 24 oriented sinusoids, linear intensity in [0.05, 1])
    translating slowly to the right; exact at any time (no resampling)."""
    rng = np.random.default_rng(7)
    k = rng.uniform(0.02, 0.25, 24)
    ang = rng.uniform(0, np.pi, 24)
    ph = rng.uniform(0, 2 * np.pi, 24)
    kx, ky = k * np.cos(ang), k * np.sin(ang)
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    times = np.arange(n, dtype=np.int64) * dt_us
    frames = np.empty((n, H, W), np.float32)
    for i, t in enumerate(times):
        xs = x - speed_pxs * t * 1e-6
        acc = np.zeros((H, W))
        for a, b, p in zip(kx, ky, ph, strict=True):
            acc += np.sin(a * xs + b * y + p)
        frames[i] = 0.05 + 0.95 / (1.0 + np.exp(-acc / 2.0))
    return frames, times


def sparse(quick: bool) -> list[BenchRow]:
    n = 200 if quick else 600
    frames, times = textured_scene(n)
    params = {"threshold_on": 0.2, "threshold_off": 0.2}
    nev = _run(frames, times, params)
    el = best_cpu_time(lambda: _run(frames, times, params), repeat=2 if quick else 3)
    ct = _copy_time(frames)
    return [BenchRow("emulator-sparse", "emulator", (n - 1) / el, "frames/s",
                     limit_ratio=ct / el,
                     extra={"events": nev, "events_per_s": nev / el,
                            "frames": n, "interpolation": "cubic",
                            "copy_frames_per_s": n / ct},
                     data=f"synthetic texture 320x240 at 20 px/s, {n} frames")]


def bar_frames(n: int):
    from evchain.sim.bar import Bar

    bar = Bar(width=W, height=H, bar_width_px=40, speed_pxs=200, x0_px=60, edge="erf",
              edge_width_px=2)
    times = np.arange(n, dtype=np.int64) * 1000
    return bar, bar.render(times), times


def bar(quick: bool) -> list[BenchRow]:
    from evchain.core.packets import EventPacket
    from evchain.report.timing import timing_errors
    from evchain.sim.bar import BarTruth

    n = 300 if quick else 1000
    bar_, frames, times = bar_frames(n)
    t0 = time.perf_counter()
    truth = BarTruth(bar_).crossing_times(0.2, 0.2, 1e-3, times[0], times[-1])
    truth_s = time.perf_counter() - t0
    ct = _copy_time(frames)
    rows = []
    for interp, name in (("cubic", "emulator-bar"), ("linear", "emulator-bar-linear")):
        params = {"threshold_on": 0.2, "threshold_off": 0.2, "eps": 1e-3,
                  "interpolation": interp}
        outs, tf = _run(frames, times, params, record=True)
        ev = EventPacket.concat(outs)
        el = best_cpu_time(lambda p=params: _run(frames, times, p), repeat=2 if quick else 3)
        e_int = timing_errors(ev.x, ev.y, ev.p, ev.t, truth, W)
        e_flt = timing_errors(ev.x, ev.y, ev.p, tf, truth, W)
        rows.append(BenchRow(
            name, "emulator", (n - 1) / el, "frames/s", error=e_int["median_abs_dt_us"],
            error_name="median |dt| us", limit_ratio=ct / el,
            extra={"events_per_s": len(ev) / el, "on": int((ev.p > 0).sum()),
                   "off": int((ev.p < 0).sum()), "interpolation": interp, "frames": n,
                   "p95_abs_dt_us": e_int["p95_abs_dt_us"],
                   "max_abs_dt_us": e_int["max_abs_dt_us"],
                   "count_diff": e_int["count_diff"],
                   "float_median_abs_dt_us": e_flt["median_abs_dt_us"],
                   "float_p95_abs_dt_us": e_flt["p95_abs_dt_us"],
                   "truth_s": truth_s, "copy_frames_per_s": n / ct},
            data=f"synthetic bar 320x240 at 200 px/s, {n} frames"))
    return rows


WORKLOADS = {"emulator-sparse": sparse, "emulator-bar": bar}
