"""Running a chain: packets stream from the source through every filter in bounded memory.

The chain times each filter (wall time, and CPU time of the calling thread) and counts what goes
in and out (``len(packet)``: events, or frames for frame packets), collects the series of the last
stage's packets, shows a progress bar over the source's time span, and writes ``report.json``
(with the CPU time of the stages after the sensor, scorers left out, per simulated second:
``cpu``) and the resolved pipeline atomically. On any error every filter's ``close()`` still runs
and the message names the filter and the slice.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from evchain.core.config import PipelineSpec
from evchain.core.filter import Context, Filter
from evchain.core.packets import FramePacket, Packet
from evchain.core.registry import Registry
from evchain.errors import EvchainError, FilterError
from evchain.io.atomic import atomic_write_text


@dataclass
class StageStats:
    name: str
    id: str
    events_in: int = 0
    events_out: int = 0
    wall_s: float = 0.0
    cpu_s: float = 0.0       # CPU time of the thread that called the filter
    unit_in: str = "events"  # what events_in counts: "events" or "frames"

    def as_dict(self) -> dict[str, Any]:
        eps = self.events_in / self.wall_s if self.wall_s > 0 else None
        return {"name": self.name, "id": self.id, "events_in": self.events_in,
                "events_out": self.events_out, "unit_in": self.unit_in, "wall_s": self.wall_s,
                "cpu_s": self.cpu_s, "throughput_eps": eps}


@dataclass
class RunResult:
    """What a run produced: the report (also written to ``out_dir/report.json``)."""

    report: dict[str, Any]
    out_dir: Path
    series: dict[str, np.ndarray] = field(default_factory=dict)


class Chain:
    """Filters set up from a validated pipeline, ready to stream."""

    def __init__(self, spec: PipelineSpec, context: Context):
        self.spec = spec
        self.context = context
        self.filters: list[Filter] = []
        self.stats: list[StageStats] = []
        self.span_us: list[int] | None = None  # first and last time the source covered
        for stage in spec.stages:
            f = stage.cls()
            f.id = stage.id
            self.filters.append(f)
            self.stats.append(StageStats(stage.use, stage.id))

    def setup(self) -> None:
        for f, stage in zip(self.filters, self.spec.stages, strict=True):
            _guard(f, None, "setup", f.setup, stage.params, self.context)

    def stream(self, progress: bool = False) -> Iterator[Packet]:
        """Yield the last stage's packets; the chain's flush packets come last."""
        source, rest = self.filters[0], self.filters[1:]
        bar = _progress_bar(source, progress)
        it = source.packets()
        try:
            while True:
                t0, c0 = time.perf_counter(), time.thread_time()
                packet = _guard(source, None, "packets", next, it, None)
                self.stats[0].wall_s += time.perf_counter() - t0
                self.stats[0].cpu_s += time.thread_time() - c0
                if packet is None:
                    break
                if self.span_us is None:
                    self.span_us = [packet.t_start, packet.t_end]
                self.span_us[1] = packet.t_end
                if self.context.debug:
                    packet.validate(f"output of {source.id!r}")
                self.stats[0].events_out += len(packet)
                if bar is not None:
                    bar.update(max(0, packet.t_end - bar.n))
                out = self._through(packet, 1)
                if out is not None:
                    yield out
            for i, f in enumerate(rest, start=1):
                t0, c0 = time.perf_counter(), time.thread_time()
                packet = _guard(f, None, "flush", f.flush)
                self.stats[i].wall_s += time.perf_counter() - t0
                self.stats[i].cpu_s += time.thread_time() - c0
                if packet is not None:
                    self.stats[i].events_out += len(packet)
                    out = self._through(packet, i + 1)
                    if out is not None:
                        yield out
        finally:
            if bar is not None:
                bar.close()

    def _through(self, packet: Packet, start: int) -> Packet:
        for i in range(start, len(self.filters)):
            f, st = self.filters[i], self.stats[i]
            st.events_in += len(packet)
            if isinstance(packet, FramePacket):
                st.unit_in = "frames"
            t0, c0 = time.perf_counter(), time.thread_time()
            packet = _guard(f, packet, "process", f.process, packet)
            st.wall_s += time.perf_counter() - t0
            st.cpu_s += time.thread_time() - c0
            if self.context.debug:
                packet.validate(f"output of {f.id!r}")
            st.events_out += len(packet)
        return packet

    def cpu_after_sensor(self) -> dict[str, Any]:
        """CPU time of the stages after the sensor (the last stage that is the source or
        declares ``sensor``: the emulator, aps), scorers left out, in all and per simulated
        second."""
        last = max(i for i, f in enumerate(self.filters) if i == 0 or f.sensor)
        counted = [i for i in range(last + 1, len(self.filters)) if not self.filters[i].scorer]
        cpu = sum(self.stats[i].cpu_s for i in counted)
        sim_s = (self.span_us[1] - self.span_us[0]) * 1e-6 if self.span_us else 0.0
        return {"after": self.stats[last].id, "stages": [self.stats[i].id for i in counted],
                "cpu_s": cpu, "simulated_s": sim_s,
                "cpu_s_per_simulated_s": cpu / sim_s if sim_s > 0 else None}

    def close(self) -> list[BaseException]:
        errors = []
        for f in self.filters:
            try:
                f.close()
            except BaseException as exc:  # every filter gets closed, whatever the others do
                errors.append(exc)
        return errors


def _guard(f: Filter, packet: Packet | None, what: str, fn, *args):
    """Call ``fn``; name the filter and the slice in any error it raises."""
    try:
        return fn(*args)
    except (StopIteration, FilterError, KeyboardInterrupt):
        raise
    except EvchainError as exc:
        raise FilterError(_where(f, packet, what) + str(exc)) from exc
    except Exception as exc:
        raise FilterError(_where(f, packet, what) + f"{type(exc).__name__}: {exc}",
                          internal=True) from exc


def _where(f: Filter, packet: Packet | None, what: str) -> str:
    where = f"filter {f.id!r} ({f.name}) failed in {what}"
    if packet is not None:
        where += f" on the slice [{packet.t_start}, {packet.t_end}) us"
    return where + ": "


def _progress_bar(source: Filter, enabled: bool):
    if not enabled:
        return None
    span = source.time_span_us()
    from tqdm import tqdm

    total = (span[1] - span[0]) if span else None
    bar = tqdm(total=total, unit="us", unit_scale=True, desc=source.id, leave=False,
               file=sys.stderr, dynamic_ncols=True, mininterval=0.5, disable=None)
    bar.n = span[0] if span else 0
    bar.total = span[1] if span else None
    return bar


def versions(registry: Registry) -> dict[str, Any]:
    import numba  # noqa: F401  (report the kernel compiler's version)

    from evchain import __version__

    return {"evchain": __version__, "python": platform.python_version(),
            "numpy": np.__version__, "numba": sys.modules["numba"].__version__,
            "plugins": {d: v for d, v in registry.distributions.items() if d != "evchain"}}


def run_pipeline(spec: PipelineSpec, registry: Registry, out_dir: str | Path,
                 progress: bool = False, debug: bool = False) -> RunResult:
    """Run ``spec`` writing into ``out_dir``; returns the report. Raises on failure after
    closing every filter and writing a report marked ``"status": "failed"``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    context = Context(seed=spec.seed, out_dir=out, debug=debug)
    resolved = spec.resolved()
    atomic_write_text(out / "pipeline.resolved.yaml", yaml.safe_dump(resolved, sort_keys=False))
    chain = Chain(spec, context)
    collected: dict[str, list[np.ndarray]] = {}
    t0 = time.perf_counter()
    status, error = "ok", None
    try:
        chain.setup()
        for packet in chain.stream(progress=progress):
            for name, entries in packet.series.items():
                collected.setdefault(name, []).append(entries)
    except BaseException as exc:
        status, error = "failed", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        close_errors = chain.close()
        if close_errors and status == "ok":
            status = "failed"
            error = "; ".join(f"{type(e).__name__}: {e}" for e in close_errors)
        series = {k: np.concatenate(v) for k, v in collected.items()}
        report = {
            "status": status,
            "error": error,
            "pipeline": resolved,
            "versions": versions(registry),
            "seed": spec.seed,
            "filters": [s.as_dict() for s in chain.stats],
            "cpu": chain.cpu_after_sensor(),
            "metrics": _jsonable(context.metrics),
            "series": {k: len(v) for k, v in series.items()},
            "wall_s": time.perf_counter() - t0,
        }
        atomic_write_text(out / "report.json", json.dumps(report, indent=2))
    if close_errors:
        raise FilterError(f"closing filters failed: {error}")
    for name, entries in series.items():
        write_series_csv(out / "series" / f"{name}.csv", entries)
    return RunResult(report=report, out_dir=out, series=series)


def write_series_csv(path: Path, entries: np.ndarray) -> None:
    """A series (structured array) as CSV with a header row, written atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    names = entries.dtype.names
    lines = [",".join(names)]
    cols = [entries[n] for n in names]
    for row in zip(*cols, strict=True):
        lines.append(",".join(repr(float(v)) if isinstance(v, np.floating) else str(v)
                              for v in row))
    atomic_write_text(path, "\n".join(lines) + "\n")


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    return value
