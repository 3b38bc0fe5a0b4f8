"""Benchmarks of the DVS emulator on three synthetic scenes made in the run, each at 320x240
(no suffix), 640x480 and 1280x720 (``-640x480``, ``-1280x720``):

- ``emulator-bar`` (and ``emulator-bar-linear``): a bar crossing the view at 200 px/s (at
  320x240), many events per frame; error = spike timing against the analytic crossing times.
- ``emulator-sparse``: a smooth random texture translating at 20 px/s, few events per frame.
- ``emulator-textured``: the same texture at 200 px/s, many events.

A larger size shows the same scene at a higher resolution: lengths and speeds in pixels scale
with the width (each pixel sees the same intensity over time, so the events per pixel and
frame stay about the same). Throughput is measured through the filter (``process`` on packets
of 100 frames, then ``flush``), best CPU time (``time.process_time``) of a few runs, one
thread: the machine is shared, so wall time would count other processes' turns.
``limit_ratio`` = CPU time of one numpy copy of the same frames into a preallocated buffer /
emulator CPU time (1.0 = as fast as touching the frames once); ``ns_per_pixel_frame`` is the
emulator's CPU time per pixel and frame. ``emulator-scaling`` states the linearity: each scene
at the three sizes on the same number of frames, its time per pixel-frame at each size and
the ratios to 320x240 (1.0 = cost linear in pixels), and the same for the 320x240 frames tiled
to the larger sizes (each pixel's input as at 320x240: only the image's size differs).
"""

from __future__ import annotations

import time

import numpy as np

from evchain.bench import BenchRow, best_cpu_time

W, H = 320, 240
#: sizes of the rows (width, height); the first is the base of the scenes' scale
SIZES = ((320, 240), (640, 480), (1280, 720))
#: frames per run (full, quick) by scene and size
FRAMES = {
    "bar": {320: (1000, 300), 640: (300, 80), 1280: (100, 30)},
    "sparse": {320: (600, 200), 640: (200, 60), 1280: (80, 30)},
    "textured": {320: (300, 100), 640: (120, 40), 1280: (50, 20)},
}
#: frames per size of ``emulator-scaling`` (full, quick): the same at every size, so that the
#: pixels' initialisation weighs the same
SCALING_FRAMES = (60, 30)
SPEEDS = {"sparse": 20.0, "textured": 200.0}


def _run(frames, times, params, record=False):
    """The output packets and, if ``record``, the float times; without ``record`` only the
    event count (timed runs): each packet is dropped once counted, as a streaming pipeline
    passes it on. Holding all of them (or joining them) makes every packet land in fresh
    memory, whose page faults (~2.7 µs per 4 KiB here) are the benchmark's cost, not the
    emulator's."""
    from evchain.core.filter import Context
    from evchain.core.packets import FramePacket, Geometry
    from evchain.filters.emulator import Emulator

    g = Geometry(frames.shape[2], frames.shape[1])
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
    return outs, np.concatenate(f.float_times) if f.float_times else np.zeros(0)


def _copy_time(frames) -> float:
    """CPU time of one copy of the frames (same float32 array the emulator reads) into a
    buffer allocated once: a fresh ``frames.copy()`` would also count page faults on a new
    output of the frames' size (~25 % more here), which the emulator never allocates."""
    out = np.empty_like(frames)
    return best_cpu_time(lambda: np.copyto(out, frames), repeat=3, warmup=True)


def _suffix(width: int, height: int) -> str:
    return "" if (width, height) == (W, H) else f"-{width}x{height}"


def textured_scene(n: int, speed_pxs: float = 20.0, dt_us: int = 1000, width: int = W,
                   height: int = H):
    """A smooth random texture (sum of 24 oriented sinusoids, linear intensity in [0.05, 1])
    translating to the right at ``speed_pxs`` (given for 320 px of width; wavelengths and
    speed scale with ``width``); exact at any time (no resampling). Each sinusoid
    sin(kx (x - v t) + ky y + phase) is split into products of a column and a row term, so a
    frame is one matrix product."""
    s = width / W
    rng = np.random.default_rng(7)
    k = rng.uniform(0.02, 0.25, 24) / s
    ang = rng.uniform(0, np.pi, 24)
    ph = rng.uniform(0, 2 * np.pi, 24)
    kx, ky = k * np.cos(ang), k * np.sin(ang)
    yv = ky[:, None] * np.arange(height)[None, :] + ph[:, None]          # [24, H]
    rows = np.concatenate([np.cos(yv), np.sin(yv)]).T                     # [H, 48]
    x = np.arange(width, dtype=np.float64)
    times = np.arange(n, dtype=np.int64) * dt_us
    frames = np.empty((n, height, width), np.float32)
    for i, t in enumerate(times):
        xv = kx[:, None] * (x[None, :] - speed_pxs * s * t * 1e-6)       # [24, W]
        acc = rows @ np.concatenate([np.sin(xv), np.cos(xv)])            # sin(a + b)
        frames[i] = 0.05 + 0.95 / (1.0 + np.exp(-acc / 2.0))
    return frames, times


def bar_frames(n: int, width: int = W, height: int = H):
    """A full-height bar (erf edges) crossing the view, 40 px wide at 200 px/s for 320 px of
    width (lengths and speed scale with ``width``); 1 kHz frames."""
    from evchain.sim.bar import Bar

    s = width / W
    bar = Bar(width=width, height=height, bar_width_px=40 * s, speed_pxs=200 * s, x0_px=60 * s,
              edge="erf", edge_width_px=2 * s)
    times = np.arange(n, dtype=np.int64) * 1000
    return bar, bar.render(times), times


def scene_frames(scene: str, n: int, width: int, height: int):
    """(frames, times) of ``scene`` (bar, sparse, textured) at this size."""
    if scene == "bar":
        return bar_frames(n, width, height)[1:]
    return textured_scene(n, SPEEDS[scene], width=width, height=height)


def _throughput_row(name, frames, times, params, quick, data) -> BenchRow:
    n, h, w = frames.shape
    nev = _run(frames, times, params)
    el = best_cpu_time(lambda: _run(frames, times, params), repeat=2 if quick else 3)
    ct = _copy_time(frames)
    return BenchRow(name, "emulator", (n - 1) / el, "frames/s", limit_ratio=ct / el,
                    extra={"events": nev, "events_per_s": nev / el, "frames": n,
                           "width": w, "height": h, "interpolation": "cubic",
                           "ns_per_pixel_frame": el / ((n - 1) * w * h) * 1e9,
                           "copy_frames_per_s": n / ct},
                    data=data)


def texture(scene: str, width: int, height: int):
    def workload(quick: bool) -> list[BenchRow]:
        n = FRAMES[scene][width][1 if quick else 0]
        frames, times = textured_scene(n, SPEEDS[scene], width=width, height=height)
        v = SPEEDS[scene] * width / W
        return [_throughput_row(f"emulator-{scene}{_suffix(width, height)}", frames, times,
                                {"threshold_on": 0.2, "threshold_off": 0.2}, quick,
                                f"synthetic texture {width}x{height} at {v:g} px/s, "
                                f"{n} frames")]
    return workload


def bar(width: int, height: int):
    def workload(quick: bool) -> list[BenchRow]:
        from evchain.core.packets import EventPacket
        from evchain.report.timing import timing_errors
        from evchain.sim.bar import BarTruth

        n = FRAMES["bar"][width][1 if quick else 0]
        bar_, frames, times = bar_frames(n, width, height)
        t0 = time.perf_counter()
        truth = BarTruth(bar_).crossing_times(0.2, 0.2, 1e-3, times[0], times[-1])
        truth_s = time.perf_counter() - t0
        ct = _copy_time(frames)
        sfx = _suffix(width, height)
        interps = (("cubic", f"emulator-bar{sfx}"),)
        if not sfx:
            interps += (("linear", "emulator-bar-linear"),)
        rows = []
        for interp, name in interps:
            params = {"threshold_on": 0.2, "threshold_off": 0.2, "eps": 1e-3,
                      "interpolation": interp}
            outs, tf = _run(frames, times, params, record=True)
            ev = EventPacket.concat(outs)
            el = best_cpu_time(lambda p=params: _run(frames, times, p), repeat=2 if quick else 3)
            e_int = timing_errors(ev.x, ev.y, ev.p, ev.t, truth, width)
            e_flt = timing_errors(ev.x, ev.y, ev.p, tf, truth, width)
            rows.append(BenchRow(
                name, "emulator", (n - 1) / el, "frames/s", error=e_int["median_abs_dt_us"],
                error_name="median |dt| us", limit_ratio=ct / el,
                extra={"events_per_s": len(ev) / el, "on": int((ev.p > 0).sum()),
                       "off": int((ev.p < 0).sum()), "interpolation": interp, "frames": n,
                       "width": width, "height": height,
                       "ns_per_pixel_frame": el / ((n - 1) * width * height) * 1e9,
                       "p95_abs_dt_us": e_int["p95_abs_dt_us"],
                       "max_abs_dt_us": e_int["max_abs_dt_us"],
                       "count_diff": e_int["count_diff"],
                       "float_median_abs_dt_us": e_flt["median_abs_dt_us"],
                       "float_p95_abs_dt_us": e_flt["p95_abs_dt_us"],
                       "truth_s": truth_s, "copy_frames_per_s": n / ct},
                data=f"synthetic bar {width}x{height} at {200 * width / W:g} px/s, "
                     f"{n} frames"))
        return rows
    return workload


def tiled(frames: np.ndarray, width: int, height: int) -> np.ndarray:
    """320x240 ``frames`` repeated to ``width`` x ``height`` (multiples of 320 and 240): every
    pixel sees what a pixel of the base image sees, so only the image's size differs."""
    return np.ascontiguousarray(np.tile(frames, (1, height // H, width // W)))


def scaling(quick: bool) -> list[BenchRow]:
    """One row per scene: its CPU time per pixel-frame at each size on the same number of
    frames, in one run (throughput: pixel-frames/s at the largest size); ``tiled_*``: the
    same for the 320x240 frames repeated to the larger sizes (the same content per pixel)."""
    n = SCALING_FRAMES[1 if quick else 0]
    params = {"threshold_on": 0.2, "threshold_off": 0.2, "eps": 1e-3}
    repeat = 2 if quick else 3
    rows = []
    for scene in ("bar", "sparse", "textured"):
        ns = {}
        base_frames, base_times = scene_frames(scene, n, W, H)
        for width, height in SIZES:
            frames, times = (base_frames, base_times) if (width, height) == (W, H) \
                else scene_frames(scene, n, width, height)
            cases = {f"{width}x{height}": frames}
            if (width, height) != (W, H):
                cases[f"tiled_{width}x{height}"] = tiled(base_frames, width, height)
            for key, f in cases.items():
                _run(f, times, params)
                el = best_cpu_time(lambda f=f, t=times: _run(f, t, params), repeat=repeat)
                ns[key] = el / ((n - 1) * width * height) * 1e9
            del frames, cases
        base = ns[f"{W}x{H}"]
        big = f"{SIZES[-1][0]}x{SIZES[-1][1]}"
        rows.append(BenchRow(
            f"emulator-scaling-{scene}", "emulator", 1e9 / ns[big], "pixel-frames/s",
            extra={"frames": n,
                   **{f"ns_per_pixel_frame_{k}": v for k, v in ns.items()},
                   **{f"per_pixel_ratio_{k}": v / base for k, v in ns.items() if k != f"{W}x{H}"}},
            data=f"{scene} scene at {', '.join(k for k in ns if not k.startswith('tiled'))}, "
                 f"and its 320x240 frames tiled to the larger sizes, {n} frames each"))
    return rows


WORKLOADS = {"emulator-scaling": scaling}
for _w, _h in SIZES:
    WORKLOADS[f"emulator-bar{_suffix(_w, _h)}"] = bar(_w, _h)
    for _scene in ("sparse", "textured"):
        WORKLOADS[f"emulator-{_scene}{_suffix(_w, _h)}"] = texture(_scene, _w, _h)
