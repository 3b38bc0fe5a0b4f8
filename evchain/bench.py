"""``evchain bench``: standard workloads, each row a throughput next to the error it reached.

Workloads come from ``evchain.benchmarks`` modules (a ``WORKLOADS`` dict) and from plugins'
``evchain_bench_workloads`` hook: ``{name: function(quick: bool) -> list[BenchRow]}``. Prefixes on
the command line select workloads by name. ``limit_ratio`` compares the stage with a physical
limit measured in the same run (e.g. a plain numpy pass over the same bytes): limit time / stage
time, so 1.0 means "as fast as touching the data once".

Every row says what it ran on (``data``) and, when it read stage parameters from a pipeline
file, which one (``params_from``). Workloads that read cached inputs (rendered drive events,
flow computed from them; :mod:`evchain.bench_cache`) are checked before anything runs: a missing
input stops the run with :class:`~evchain.errors.MissingBenchInput`, naming the
``evchain bench --prepare`` command that makes it. :func:`prepare` makes the inputs and runs no
rows.
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evchain.bench_cache import BenchInput, inputs_of
from evchain.errors import MissingBenchInput
from evchain.io.atomic import atomic_write_text


@dataclass
class BenchRow:
    """One result. ``data``: what the row ran on (e.g. ``reference-drive 0-2 s @3fa9c01b2e``,
    ``DVSFLOW16 TranslatingSquare``), including whose parameters when they are the thesis's or
    defaults; ``params_from``: the pipeline file (relative to the repository) whose stage
    parameters the row read, else None. :func:`run` fills ``repeat`` (0-based) and
    ``command`` (the ``evchain bench`` command line that makes the row again)."""

    workload: str
    stage: str
    throughput: float
    unit: str
    error: float | None = None
    error_name: str | None = None
    limit_ratio: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    data: str | None = None
    params_from: str | None = None
    repeat: int = 0
    command: str | None = None

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        extra = d.pop("extra")
        clash = sorted(set(extra) & set(d))
        if clash:
            raise ValueError(f"row {self.workload}: extra keys {clash} clash with BenchRow fields")
        d.update(extra)
        return d


def best_time(fn: Callable[[], object], repeat: int = 3, min_time_s: float = 0.0) -> float:
    """Best wall time of ``repeat`` calls (after one warm-up call that also compiles)."""
    fn()
    best = float("inf")
    start = time.perf_counter()
    n = 0
    while n < repeat or time.perf_counter() - start < min_time_s:
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
        n += 1
    return best


def best_cpu_time(fn: Callable[[], object], repeat: int = 3, warmup: bool = False,
                  clock: Callable[[], float] = time.process_time) -> float:
    """Best CPU time of ``repeat`` calls: on a shared machine wall time also counts the other
    processes' turns. ``clock`` may be ``time.thread_time`` for one thread's share."""
    if warmup:
        fn()
    best = float("inf")
    for _ in range(max(repeat, 1)):
        t0 = clock()
        fn()
        best = min(best, clock() - t0)
    return max(best, 1e-9)


def cut_every(packet, packet_us: int = 10_000) -> list:
    """``packet`` cut into consecutive slices of ``packet_us`` (the last one may be shorter)."""
    from evchain.testing.contract import recut

    return recut([packet], list(range(packet.t_start + packet_us, packet.t_end, packet_us)))


def _file_parts(path: Path) -> list[Path]:
    """The files of ``path``: itself, or every file below it (formats stored as folders)."""
    return sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]


def source_row(workload: str, cls, params: dict[str, Any], path: Path, events: int,
               extra: dict[str, Any] | None = None, data: str | None = None) -> BenchRow:
    """Row for a file source reading ``path`` (``events`` events) in events/s; ``limit_ratio``
    = time of ``np.fromfile`` over the same bytes / time of the source. ``data``: what the file
    holds."""
    from evchain.testing.contract import run_source

    def stage():
        got = sum(len(p) for p in run_source(cls, params, path.parent)[0])
        if got != events:
            raise RuntimeError(f"{cls.name} read {got} events from {path}, expected {events}")

    t_stage = best_time(stage)
    cpu = best_cpu_time(stage)
    parts = _file_parts(path)
    t_limit = best_time(lambda: [np.fromfile(f, np.uint8) for f in parts])
    return BenchRow(workload, cls.name, events / t_stage, "events/s", None, None,
                    t_limit / t_stage, {"events": events, "cpu_time_eps": events / cpu,
                                        "bytes": sum(f.stat().st_size for f in parts),
                                        **(extra or {})}, data=data)


def imu_source_row(workload: str, cls, params: dict[str, Any], path: Path, samples: int,
                   events: int, data: str) -> BenchRow:
    """Row for a source reading the IMU samples of ``path`` (``samples`` of them, beside
    ``events`` events, all read) in samples per CPU second of the whole read; checks that every
    sample arrives in the series ``imu``."""
    from evchain.testing.contract import run_source

    def stage():
        packets = run_source(cls, params, path.parent)[0]
        got = sum(len(p.series.get("imu", ())) for p in packets)
        if got != samples:
            raise RuntimeError(f"{cls.name} read {got} IMU samples from {path}, expected "
                               f"{samples}")

    cpu = best_cpu_time(stage, warmup=True)
    wall = best_time(stage, repeat=1)
    return BenchRow(workload, cls.name, samples / cpu, "samples/s (CPU)", None, None, None,
                    {"samples": samples, "events": events, "throughput_wall": samples / wall,
                     "bytes": sum(f.stat().st_size for f in _file_parts(path))}, data=data)


def sink_row(workload: str, cls, packets: list, out_dir: Path, name: str,
             params: dict[str, Any] | None = None,
             extra: dict[str, Any] | None = None, data: str | None = None) -> BenchRow:
    """Row for a file writer writing ``packets`` to ``out_dir/name`` in events/s (``name`` has a
    ``{}`` for the run number: replacing a big file costs more than writing a new one);
    ``limit_ratio`` = time of ``ndarray.tofile`` of the same bytes / time of the writer.
    ``data``: what the packets hold."""
    from evchain.testing.contract import run_sink

    runs = itertools.count()
    events = sum(len(p) for p in packets)

    def stage():
        run_sink(cls, {"path": name.format(next(runs)), **(params or {})}, packets, out_dir)

    t_stage = best_time(stage, repeat=2)
    cpu = best_cpu_time(stage, repeat=1)
    written = np.concatenate([np.fromfile(f, np.uint8)
                              for f in _file_parts(out_dir / name.format(0))])
    t_limit = best_time(lambda: written.tofile(out_dir / f"plain{next(runs)}.bin"))
    return BenchRow(workload, cls.name, events / t_stage, "events/s", None, None,
                    t_limit / t_stage, {"events": events, "cpu_time_eps": events / cpu,
                                        **(extra or {})}, data=data)


def select(workloads: dict[str, Callable], prefixes: list[str],
           exact: bool = False) -> dict[str, Callable]:
    """The workloads whose names start with one of ``prefixes`` (``exact``: equal one of them);
    all without ``prefixes``."""
    if not prefixes:
        return dict(workloads)
    if exact:
        return {k: v for k, v in workloads.items() if k in prefixes}
    return {k: v for k, v in workloads.items() if any(k.startswith(p) for p in prefixes)}


def command(name: str, quick: bool) -> str:
    """The command line that runs workload ``name`` again, and no other (``foe-map`` is also
    the start of ``foe-map-cell2``)."""
    return f"evchain bench --exact {name}" + (" --quick" if quick else "")


def _prepare_command(names: list[str], quick: bool) -> str:
    return " ".join(["evchain bench --prepare", *names] + (["--quick"] if quick else []))


def missing_inputs(workloads: dict[str, Callable], quick: bool
                   ) -> dict[str, list[BenchInput]]:
    """``{workload: [inputs not in the cache]}`` for the workloads with missing inputs."""
    out = {}
    for name in sorted(workloads):
        missing = [i for i in inputs_of(workloads[name], quick) if not i.exists()]
        if missing:
            out[name] = missing
    return out


def check_inputs(workloads: dict[str, Callable], quick: bool,
                 selection: list[str] | None = None) -> None:
    """Raise :class:`MissingBenchInput` naming every missing input and the command that makes
    them (for ``selection``, the command-line words that selected ``workloads``, else for the
    workloads that lack inputs); nothing is substituted."""
    missing = missing_inputs(workloads, quick)
    if not missing:
        return
    lines = [f"{name} needs {inp.describe()} ({inp.path})"
             for name, inputs in missing.items() for inp in inputs]
    raise MissingBenchInput(
        "benchmark inputs are not prepared:\n  " + "\n  ".join(lines) + "\nmake them with: "
        + _prepare_command(sorted(missing) if selection is None else selection, quick))


def prepare(workloads: dict[str, Callable], quick: bool = False, echo=print) -> list[BenchInput]:
    """Make the cached inputs the ``workloads`` read (with ``quick``: those of the quick rows)
    that are missing; runs no rows. Returns the inputs made."""
    made, seen = [], set()
    for name in sorted(workloads):
        for inp in inputs_of(workloads[name], quick):
            if inp.path in seen:
                continue
            seen.add(inp.path)
            if inp.prepare(echo):
                made.append(inp)
            else:
                echo(f"{name}: have {inp.describe()}")
    return made


def run(workloads: dict[str, Callable], quick: bool = False, repeat: int = 1,
        echo=print) -> list[BenchRow]:
    """Run every workload ``repeat`` times (round-robin: repeat 0 of all, then repeat 1, ...)
    after checking that their cached inputs exist. Each row gets ``repeat`` and ``command``."""
    check_inputs(workloads, quick)
    rows: list[BenchRow] = []
    with one_blas_thread():
        for i in range(repeat):
            for name in sorted(workloads):
                got = workloads[name](quick)
                if not got:
                    echo(f"{name}: no rows (its data is not available here)")
                for row in got:
                    if not row.data:
                        raise ValueError(f"workload {name}: row {row.workload} does not say "
                                         "what it ran on (BenchRow.data)")
                    row.repeat, row.command = i, command(name, quick)
                    echo(format_row(row))
                rows.extend(got)
    return rows


def one_blas_thread():
    """A context in which numpy's BLAS runs on one thread. Its worker threads (OpenBLAS) spin
    for a while after each matrix product, and CPU time (``time.process_time``) counts every
    thread of the process: a workload that makes its data with a matrix product (the
    emulator's textures) would otherwise charge their spinning to the stage it times (the
    emulator's CPU time per frame on 100 textured frames came out 1.5-2 times its own).
    The limit covers the libraries loaded when it is set, so scipy's own OpenBLAS (scipy
    imported by a workload, e.g. the bar's error function) is loaded first."""
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


HEADER = (f"{'workload':34s} {'stage':16s} {'throughput':>14s} {'unit':10s} "
          f"{'error':>12s} {'error_name':24s} {'limit':>7s}  data [params from]")


def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def format_row(r: BenchRow) -> str:
    params = f" [{r.params_from}]" if r.params_from else ""
    return (f"{r.workload:34s} {r.stage:16s} {_num(r.throughput, '14.4g')} {r.unit:10s} "
            f"{_num(r.error, '12.4g')} {(r.error_name or '-'):24s} "
            f"{_num(r.limit_ratio, '7.3f')}  {r.data or '-'}{params}")


def write_json(rows: list[BenchRow], path: str | Path) -> None:
    """A JSON list of the rows' dicts (fields, then the extras), every repeat's rows."""
    atomic_write_text(path, json.dumps([r.as_dict() for r in rows], indent=2))
