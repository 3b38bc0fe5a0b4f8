"""Other projects' DVS emulators side by side with evchain's, on the very frames of the
emulator benchmarks (:mod:`evchain.benchmarks.emulator`): ``emulator-peer-<scene>[-WxH]``.

Peers, used only when importable (neither is a dependency of evchain, and none of their code
is in it; docs/explanation/emulator.md, "Peers", says how to make them importable):

- ``esim``: ESIM's C++ event simulator core, the Python module ``esim_py`` built with an entry
  ``EventSimulator.generateFromFloatFrames(frames, timestamps_s)`` that takes float32 frames
  ``[n, h, w]`` in memory (the stock module reads image files only); log intensity
  ``ln(I + eps)`` in float32, linear between frames, strict comparisons.
- ``v2e``: v2e's ``v2ecore.emulator.EventEmulator`` (torch, CPU, one thread), fed the frames'
  ``ln(I + eps)`` (``hdr=True``) with its noise, leak, photoreceptor low-pass and refractory
  period off.

Each row is one peer on one workload: its frames per CPU second (``time.process_time``, best
of a few runs; all threads of the process count; the peer's own call, its output as it gives
it, not the conversion to evchain's columns), ``speedup`` = the peer's CPU time / evchain's
on the same frames in the same run (evchain's default cubic interpolation, as in the emulator
rows), and on the bar the peer's timing error (median |dt| against the analytic crossings).
A workload whose peers are all absent gives no rows and says on stderr what is missing.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from typing import Protocol

import numpy as np

from evchain.bench import BenchRow, best_cpu_time
from evchain.benchmarks.emulator import FRAMES, SIZES, _run, _suffix, bar_frames, scene_frames

#: the emulator's parameters on every workload (natural log units)
THRESHOLD = 0.2
EPS = 1e-3
HOW = ("see docs/explanation/emulator.md, \"Peers\", for how to make it importable "
       "(it is not a dependency of evchain)")


class Peer(Protocol):
    """An emulator to run side by side: ``run(frames, times_us)`` emulates float32 frames
    ``[n, H, W]`` (linear intensity) at integer µs times and returns the peer's output as it
    gives it (what is timed); ``events(output)`` gives that output's events as float64
    columns ``[N, 4]``: x, y, t (µs), polarity (+1/-1)."""

    name: str

    def run(self, frames: np.ndarray, times_us: np.ndarray) -> object: ...

    def events(self, output: object) -> np.ndarray: ...


class EsimPeer:
    """ESIM's core through ``esim_py`` (with the in-memory float-frame entry)."""

    name = "esim"

    def __init__(self, module):
        self.module = module

    def run(self, frames, times_us):
        sim = self.module.EventSimulator(THRESHOLD, THRESHOLD, 0.0, EPS, True)
        return sim.generateFromFloatFrames(np.ascontiguousarray(frames, np.float32),
                                           [float(t) * 1e-6 for t in times_us])

    def events(self, output):
        ev = np.asarray(output)                       # x, y, t (s), polarity
        out = np.empty((len(ev), 4))
        if len(ev):
            out[:, 0], out[:, 1] = ev[:, 0], ev[:, 1]
            out[:, 2] = ev[:, 2] * 1e6
            out[:, 3] = np.where(ev[:, 3] > 0, 1.0, -1.0)
        return out


class V2ePeer:
    """v2e's ``EventEmulator`` on the log frames (``hdr=True``), non-idealities off, CPU."""

    name = "v2e"

    def __init__(self, emulator_cls, torch):
        self.emulator_cls = emulator_cls
        self.torch = torch

    def run(self, frames, times_us):
        self.torch.set_num_threads(1)
        # its per-frame "no signal events" warnings would be written (and timed) otherwise
        logging.getLogger("v2ecore.emulator").setLevel(logging.ERROR)
        emu = self.emulator_cls(pos_thres=THRESHOLD, neg_thres=THRESHOLD, sigma_thres=0.0,
                                cutoff_hz=0.0, leak_rate_hz=0.0, shot_noise_rate_hz=0.0,
                                refractory_period_s=0.0, device="cpu", hdr=True)
        logs = np.log(frames.astype(np.float64) + EPS).astype(np.float32)
        return [emu.generate_events(frame, float(t) * 1e-6)
                for frame, t in zip(logs, times_us, strict=True)]

    def events(self, output):
        parts = [np.asarray(ev, np.float64) for ev in output if ev is not None and len(ev)]
        if not parts:
            return np.empty((0, 4))
        ev = np.concatenate(parts)                    # t (s), x, y, p
        return np.column_stack([ev[:, 1], ev[:, 2], ev[:, 0] * 1e6,
                                np.where(ev[:, 3] > 0, 1.0, -1.0)])


def find_esim() -> Peer | str:
    """The ESIM peer, or why it is absent."""
    try:
        import esim_py
    except Exception as exc:                          # noqa: BLE001 (any import failure)
        return f"ESIM's core (esim_py) is not importable ({type(exc).__name__}: {exc}); {HOW}"
    if not hasattr(esim_py.EventSimulator, "generateFromFloatFrames"):
        return ("esim_py has no EventSimulator.generateFromFloatFrames (the stock module reads "
                f"image files only); {HOW}")
    return EsimPeer(esim_py)


def find_v2e() -> Peer | str:
    """The v2e peer, or why it is absent."""
    try:
        import torch
        from v2ecore.emulator import EventEmulator
    except Exception as exc:                          # noqa: BLE001 (any import failure)
        return (f"v2e's emulator (v2ecore.emulator with torch) is not importable "
                f"({type(exc).__name__}: {exc}); {HOW}")
    return V2ePeer(EventEmulator, torch)


#: how each peer is found (a test may replace them)
FINDERS: list[Callable[[], Peer | str]] = [find_esim, find_v2e]


def peers() -> tuple[list[Peer], list[str]]:
    """(the importable peers, the reasons why the others are absent)."""
    found, absent = [], []
    for find in FINDERS:
        p = find()
        (absent if isinstance(p, str) else found).append(p)
    return found, absent


def _median_abs_dt(ev: np.ndarray, truth, width: int) -> tuple[float, int]:
    from evchain.report.timing import timing_errors

    e = timing_errors(ev[:, 0].astype(np.int64), ev[:, 1].astype(np.int64),
                      ev[:, 3].astype(np.int8), ev[:, 2], truth, width)
    return e["median_abs_dt_us"], e["count_diff"]


def peer_workload(scene: str, width: int, height: int):
    name = f"emulator-peer-{scene}{_suffix(width, height)}"

    def workload(quick: bool) -> list[BenchRow]:
        found, absent = peers()
        for why in absent:
            print(f"{name}: {why}", file=sys.stderr)
        if not found:
            return []
        n = FRAMES[scene][width][1]
        truth = None
        if scene == "bar":
            from evchain.sim.bar import BarTruth

            bar_, frames, times = bar_frames(n, width, height)
            truth = BarTruth(bar_).crossing_times(THRESHOLD, THRESHOLD, EPS, times[0], times[-1])
        else:
            frames, times = scene_frames(scene, n, width, height)
        params = {"threshold_on": THRESHOLD, "threshold_off": THRESHOLD, "eps": EPS}
        repeat = 2 if quick else 3
        own = best_cpu_time(lambda: _run(frames, times, params), repeat=repeat, warmup=True)
        rows = []
        for peer in found:
            ev = peer.events(peer.run(frames, times))
            el = best_cpu_time(lambda p=peer: p.run(frames, times), repeat=repeat)
            err, count_diff = (None, None) if truth is None else _median_abs_dt(ev, truth, width)
            rows.append(BenchRow(
                f"emulator-peer-{peer.name}-{scene}{_suffix(width, height)}", peer.name,
                (n - 1) / el, "frames/s", error=err,
                error_name=None if err is None else "median |dt| us",
                extra={"events": len(ev), "ms_per_frame": el / (n - 1) * 1e3,
                       "evchain_ms_per_frame": own / (n - 1) * 1e3, "speedup": el / own,
                       "count_diff": count_diff, "frames": n},
                data=f"the frames of emulator-{scene}{_suffix(width, height)}: "
                     f"{width}x{height}, {n} frames"))
        return rows
    return workload


WORKLOADS = {f"emulator-peer-{scene}{_suffix(w, h)}": peer_workload(scene, w, h)
             for w, h in SIZES for scene in ("bar", "sparse", "textured")}
