"""Running a chain: packets stream from the source through every filter in bounded memory.

Each stage runs on a thread of its own, joined to the next by a bounded queue
(:mod:`evchain.core.stage_threads`; ``threads=False``: all on the calling thread, the same
results). The chain times each filter (wall time, and CPU time of the thread that runs it) and
counts what goes in and out (``len(packet)``: events, or frames for frame packets), streams the
series of the last stage's packets to CSV files as they come (memory does not grow with the
recording), shows a progress bar over the source's time span, and writes ``report.json`` (with
the CPU time of the stages after the sensor, scorers left out, per simulated second: ``cpu``)
and the resolved pipeline atomically. A run first marks its folder as in progress
(``report.json`` says ``running``; the files it will write are removed). On any error every
filter's ``close()`` still runs and the message names the filter and the slice.

Ctrl-C (SIGINT) stops a run cleanly, whatever the source: the first one sets
``Context.stop``, the chain ends the stream after the packets in flight, flushes and closes
every filter, so that the outputs are complete up to there; ``report.json`` says
``interrupted`` and :class:`~evchain.errors.RunInterrupted` is raised. A second Ctrl-C aborts
at once, as a failure (outputs left as ``.partial``).
"""

from __future__ import annotations

import json
import logging
import platform
import shutil
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from evchain.core.config import PipelineSpec
from evchain.core.filter import Context, Filter
from evchain.core.packets import FramePacket, Packet
from evchain.core.registry import Registry
from evchain.core.stage_threads import StageThreads, in_order
from evchain.errors import ConfigError, EvchainError, FilterError, RunInterrupted
from evchain.io.atomic import atomic_write_text, partial_path
from evchain.io.series_csv import SeriesCsvWriter, remove_series
from evchain.provenance import input_digests, source_stamps


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
    """What a run produced: the report (also written to ``out_dir/report.json``); the series
    are in ``out_dir/series/NAME.csv``."""

    report: dict[str, Any]
    out_dir: Path


class Chain:
    """Filters set up from a validated pipeline, ready to stream. With ``threads`` each stage
    runs on a thread of its own (:mod:`evchain.core.stage_threads`), every call of its filter
    from set-up to close; else every stage on the calling thread."""

    def __init__(self, spec: PipelineSpec, context: Context, threads: bool = True):
        self.spec = spec
        self.context = context
        self.filters: list[Filter] = []
        self.stats: list[StageStats] = []
        self.span_us: list[int] | None = None  # first and last time the source covered
        self.stopped = False  # the source was left early: Context.stop (Ctrl-C)
        for stage in spec.stages:
            f = stage.cls()
            f.id = stage.id
            self.filters.append(f)
            self.stats.append(StageStats(stage.use, stage.id))
        self._threads = StageThreads(len(self.filters)) if threads else None

    def _call(self, i: int, fn, *args):
        """``fn(*args)`` for stage i: on its thread, or here without threads."""
        return fn(*args) if self._threads is None else self._threads.call(i, fn, *args)

    def setup(self) -> None:
        for i, (f, stage) in enumerate(zip(self.filters, self.spec.stages, strict=True)):
            self._call(i, _guard, f, None, "setup", f.setup, stage.params, self.context)

    def stream(self, progress: bool = False) -> Iterator[Packet]:
        """Yield the last stage's packets; the chain's flush packets come last (each stage's
        flushed once the stream has passed every stage, with or without threads). Once
        ``context.stop`` is set no further packet is taken from the source (its iterator is
        closed; a source that ``ends_on_stop`` ends its stream itself) and the filters are
        flushed as at the end of the stream."""
        from evchain.core.progress import RunProgress

        bar = RunProgress(self.filters[0].id, self.filters[0].time_span_us(), progress)
        stages = [_Timed(f, st, self.context.debug)
                  for f, st in zip(self.filters[1:], self.stats[1:], strict=True)]
        try:
            if self._threads is None:
                yield from in_order(self._source(bar), stages)
            else:
                yield from self._threads.stream(lambda: self._source(bar), stages)
        finally:
            bar.close()

    def _source(self, bar) -> Iterator[Packet]:
        """The source's packets, timed and counted, until its end or ``context.stop``."""
        source = self.filters[0]
        it = source.packets()
        stop = self.context.stop
        while source.ends_on_stop or not stop.is_set():
            packet = _timed(self.stats[0], source, None, "packets", next, it, None)
            if packet is None:
                break
            if self.span_us is None:
                self.span_us = [packet.t_start, packet.t_end]
            self.span_us[1] = packet.t_end
            if self.context.debug:
                packet.validate(f"output of {source.id!r}")
            self.stats[0].events_out += len(packet)
            bar.update(packet.t_end)
            yield packet
        if stop.is_set():
            self.stopped = True
            if hasattr(it, "close"):  # a generator's finally blocks run now
                _guard(source, None, "packets", it.close)

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
        """Close every filter (on its thread), whatever the others do; the errors raised. The
        stage threads end here."""
        errors = []
        for i, f in enumerate(self.filters):
            try:
                self._call(i, f.close)
            except BaseException as exc:
                errors.append(exc)
        if self._threads is not None:
            self._threads.close()
            self._threads = None
        return errors


class _Timed:
    """A filter as a stage of :mod:`evchain.core.stage_threads`: each call timed (wall, and
    CPU of the thread that runs it), counted and guarded (:func:`_guard`)."""

    def __init__(self, f: Filter, stats: StageStats, debug: bool):
        self.f, self.stats, self.debug = f, stats, debug

    def process(self, packet: Packet) -> Packet:
        f, st = self.f, self.stats
        st.events_in += len(packet)
        if isinstance(packet, FramePacket):
            st.unit_in = "frames"
        out = _timed(st, f, packet, "process", f.process, packet)
        if self.debug:
            out.validate(f"output of {f.id!r}")
        st.events_out += len(out)
        return out

    def flush(self) -> Packet | None:
        f, st = self.f, self.stats
        out = _timed(st, f, None, "flush", f.flush)
        if out is not None:
            st.events_out += len(out)
        return out


def _timed(st: StageStats, f: Filter, packet: Packet | None, what: str, fn, *args):
    """:func:`_guard`, its wall time and the CPU time of the calling thread added to ``st``."""
    t0, c0 = time.perf_counter(), time.thread_time()
    out = _guard(f, packet, what, fn, *args)
    st.wall_s += time.perf_counter() - t0
    st.cpu_s += time.thread_time() - c0
    return out


def _guard(f: Filter, packet: Packet | None, what: str, fn, *args):
    """Call ``fn``; name the filter and the slice in any error it raises."""
    try:
        return fn(*args)
    except (StopIteration, FilterError, KeyboardInterrupt):
        raise
    except EvchainError as exc:
        raise FilterError(_where(f, packet, what) + str(exc)) from exc
    except OSError as exc:
        if exc.filename is None:  # not about a file the user named
            raise FilterError(_where(f, packet, what) + f"{type(exc).__name__}: {exc}",
                              internal=True) from exc
        raise FilterError(_where(f, packet, what) + f"{exc.filename}: {exc.strerror}") from exc
    except Exception as exc:
        raise FilterError(_where(f, packet, what) + f"{type(exc).__name__}: {exc}",
                          internal=True) from exc


def _where(f: Filter, packet: Packet | None, what: str) -> str:
    where = f"filter {f.id!r} ({f.name}) failed in {what}"
    if packet is not None:
        where += f" on the slice [{packet.t_start}, {packet.t_end}) us"
    return where + ": "


def versions(registry: Registry, spec: PipelineSpec | None = None) -> dict[str, Any]:
    """The versions of evchain, Python, numpy, numba and the plugins, and the source hashes
    (:func:`evchain.provenance.source_stamps`: with ``spec``, of the code a run of it can
    execute)."""
    import numba  # noqa: F401  (report the kernel compiler's version)

    from evchain import __version__

    return {"evchain": __version__, "python": platform.python_version(),
            "numpy": np.__version__, "numba": sys.modules["numba"].__version__,
            "plugins": {d: v for d, v in registry.distributions.items() if d != "evchain"},
            "source": source_stamps(registry, spec)}


def run_pipeline(spec: PipelineSpec, registry: Registry, out_dir: str | Path,
                 progress: bool = False, debug: bool = False,
                 threads: bool = True) -> RunResult:
    """Run ``spec`` writing into ``out_dir``; returns the report (with what made the run: the
    resolved pipeline, each input file's SHA-256 and the versions and source hashes of the
    code). ``threads``: each stage on a thread of its own (:class:`Chain`; the same
    results), else every stage on the calling thread. The folder is marked as in progress
    first (:func:`start_run_folder`); series are written as they come. Raises on failure
    after closing every filter and writing a report marked ``"status": "failed"``; after a
    Ctrl-C, raises :class:`RunInterrupted` once every filter was flushed and closed and the
    report says ``"status": "interrupted"``."""
    out = Path(out_dir)
    _make_run_folder(out)
    resolved = spec.resolved()
    made_by = {"pipeline": resolved, "inputs": input_digests(spec),
               "versions": versions(registry, spec), "seed": spec.seed}
    start_run_folder(spec, out, made_by)
    atomic_write_text(out / "pipeline.resolved.yaml", yaml.safe_dump(resolved, sort_keys=False))
    context = Context(seed=spec.seed, out_dir=out, debug=debug)
    chain = Chain(spec, context, threads=threads)
    series = SeriesCsvWriter(out / "series")
    t0 = time.perf_counter()
    status, error = "ok", None
    try:
        with stop_on_interrupt(context.stop):
            chain.setup()
            with closing(chain.stream(progress=progress)) as packets:
                for packet in packets:  # closed (its threads joined) before the filters
                    series.append(packet.series)
        if chain.stopped:
            status = "interrupted"
            end = f" at {chain.span_us[1]} us" if chain.span_us else " before the first packet"
            error = (f"interrupted (Ctrl-C){end}: every filter was flushed and the outputs in "
                     f"{out}/ are complete up to there")
    except BaseException as exc:
        status, error = "failed", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        close_errors = chain.close()
        if close_errors and status != "failed":
            status = "failed"
            error = "; ".join(f"{type(e).__name__}: {e}" for e in close_errors)
        if status in ("ok", "interrupted"):
            series.commit()
        else:
            series.abort()
        report = {
            "status": status,
            "error": error,
            **made_by,
            "filters": [s.as_dict() for s in chain.stats],
            "cpu": chain.cpu_after_sensor(),
            "metrics": _jsonable(context.metrics),
            "warnings": list(context.warnings),
            "series": dict(series.counts),
            "wall_s": time.perf_counter() - t0,
        }
        atomic_write_text(out / "report.json", json.dumps(report, indent=2))
    if close_errors:
        raise FilterError(f"closing filters failed: {error}")
    result = RunResult(report=report, out_dir=out)
    if status == "interrupted":
        raise RunInterrupted(error, result, chain.span_us[1] if chain.span_us else None)
    return result


@contextmanager
def stop_on_interrupt(stop: threading.Event):
    """While inside, the first SIGINT (Ctrl-C) sets ``stop`` instead of raising
    :class:`KeyboardInterrupt`; a second one raises it. Signals reach the main thread only:
    elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        logging.getLogger("evchain").warning(
            "stopping: finishing the packets in flight and writing the outputs "
            "(Ctrl-C again to abort)")

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None
                      else signal.default_int_handler)


def start_run_folder(spec: PipelineSpec, out: Path, report: dict[str, Any]) -> None:
    """Mark ``out`` as holding a run in progress before anything runs: ``report.json`` is
    rewritten with ``"status": "running"`` (and ``report``'s fields), then every file this run
    will write is removed (the series, each stage's ``output_files`` and their ``.partial``
    files), so nothing an earlier run left there looks current, even after a crash."""
    atomic_write_text(out / "report.json",
                      json.dumps({"status": "running", "error": None, **report}, indent=2))
    remove_series(out / "series")
    root = out.resolve()
    for stage in spec.stages:
        for rel in stage.cls.output_files(stage.params):
            for path in (out / rel, partial_path(out / rel)):
                inside = root in path.resolve().parents  # never the folder itself or above
                if inside and path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                elif inside and (path.exists() or path.is_symlink()):
                    path.unlink()


def _make_run_folder(out: Path) -> None:
    """Create the run folder; one that cannot be (a file there, no permission) is a ConfigError."""
    import os

    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out} exists and is not a folder: choose another run folder",
                          file="--out")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the run folder {out}: {exc.strerror}",
                          file="--out") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(f"cannot write into the run folder {out}: permission denied",
                          file="--out")


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
