"""``evchain bench``: standard workloads, each row a throughput next to the error it reached.

Workloads come from ``evchain.benchmarks`` modules (a ``WORKLOADS`` dict) and from plugins'
``evchain_bench_workloads`` hook: ``{name: function(quick: bool) -> list[BenchRow]}``. Prefixes on
the command line select workloads by name. ``limit_ratio`` compares the stage with a physical
limit measured in the same run (e.g. a plain numpy pass over the same bytes): limit time / stage
time, so 1.0 means "as fast as touching the data once".
"""

from __future__ import annotations

import hashlib
import itertools
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evchain.io.atomic import atomic_write_text


@dataclass
class BenchRow:
    workload: str
    stage: str
    throughput: float
    unit: str
    error: float | None = None
    error_name: str | None = None
    limit_ratio: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        extra = d.pop("extra")
        d.update(extra)
        return d


_PACKAGE = Path(__file__).resolve().parent

#: the sources that make the simulator's events: a cache of rendered events is valid for them only
SIMULATOR_SOURCES = ("sim", "kernels/scene.py", "kernels/emulator.py", "kernels/veclog.py",
                     "kernels/intrinsics.py", "filters/scene.py", "filters/emulator.py")


def source_stamp(*sources: str) -> str:
    """Short hash of the package's source files (``sources``: paths or folders relative to the
    ``evchain`` package), for the names of cached benchmark inputs: a cache made by other code is
    not found and gets remade instead of silently reused."""
    h = hashlib.sha256()
    for rel in sources:
        p = _PACKAGE / rel
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(f.relative_to(_PACKAGE).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:10]


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
               extra: dict[str, Any] | None = None) -> BenchRow:
    """Row for a file source reading ``path`` (``events`` events) in events/s; ``limit_ratio``
    = time of ``np.fromfile`` over the same bytes / time of the source."""
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
                                        **(extra or {})})


def sink_row(workload: str, cls, packets: list, out_dir: Path, name: str,
             params: dict[str, Any] | None = None,
             extra: dict[str, Any] | None = None) -> BenchRow:
    """Row for a file writer writing ``packets`` to ``out_dir/name`` in events/s (``name`` has a
    ``{}`` for the run number: replacing a big file costs more than writing a new one);
    ``limit_ratio`` = time of ``ndarray.tofile`` of the same bytes / time of the writer."""
    from evchain.testing.contract import run_sink

    runs = itertools.count()
    events = sum(len(p) for p in packets)

    def stage():
        run_sink(cls, {"path": name.format(next(runs)), **(params or {})}, packets, out_dir)

    t_stage = best_time(stage, repeat=2)
    cpu = best_cpu_time(stage, repeat=1)
    data = np.concatenate([np.fromfile(f, np.uint8)
                           for f in _file_parts(out_dir / name.format(0))])
    t_limit = best_time(lambda: data.tofile(out_dir / f"plain{next(runs)}.bin"))
    return BenchRow(workload, cls.name, events / t_stage, "events/s", None, None,
                    t_limit / t_stage, {"events": events, "cpu_time_eps": events / cpu,
                                        **(extra or {})})


def select(workloads: dict[str, Callable], prefixes: list[str]) -> dict[str, Callable]:
    if not prefixes:
        return dict(workloads)
    return {k: v for k, v in workloads.items() if any(k.startswith(p) for p in prefixes)}


def run(workloads: dict[str, Callable], quick: bool = False, echo=print) -> list[BenchRow]:
    rows: list[BenchRow] = []
    for name in sorted(workloads):
        got = workloads[name](quick)
        for row in got:
            echo(format_row(row))
        rows.extend(got)
    return rows


HEADER = (f"{'workload':34s} {'stage':16s} {'throughput':>14s} {'unit':10s} "
          f"{'error':>12s} {'error_name':24s} {'limit':>7s}")


def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def format_row(r: BenchRow) -> str:
    return (f"{r.workload:34s} {r.stage:16s} {_num(r.throughput, '14.4g')} {r.unit:10s} "
            f"{_num(r.error, '12.4g')} {(r.error_name or '-'):24s} "
            f"{_num(r.limit_ratio, '7.3f')}")


def write_json(rows: list[BenchRow], path: str | Path) -> None:
    atomic_write_text(path, json.dumps([r.as_dict() for r in rows], indent=2))
