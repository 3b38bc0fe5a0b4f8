"""``evchain sweep``: variations of pipelines, run in parallel, cached, tabulated.

A sweep file::

    name: threshold                     # optional, defaults to the file's stem
    base: ../reference-lk.yaml          # relative to the sweep file
    mode: one_at_a_time                 # or: grid (every combination)
    set: [scene.duration_s=6]           # overrides applied to every run (optional)
    vary:
      scene.speed_mps: [10, 20, 30]
      emulator.threshold_on,emulator.threshold_off: [[10, 10], [20, 20], [40, 40]]
    report: [foe.dx_mean_px, foe.dy_mean_px, ttc.median_rel_error_last3s]

``evchain sweep --set STAGE.PARAM=VALUE`` (repeatable) appends to ``set`` for this run of the
sweep: a variant of a whole sweep without a copy of its file (each variation's own overrides
still come after it; give ``--out`` to keep the variant's table apart).

``report`` keys name metrics (``GROUP.NAME`` of ``report.json``'s ``metrics``) or the run's CPU
time after the sensor (``cpu.cpu_s_per_simulated_s``, ``cpu.cpu_s``: ``report.json``'s ``cpu``).

A key naming several parameters, separated by commas, sets them together from a list per value.
``one_at_a_time`` varies one key while the others keep the base's values (as the thesis's
tables do); ``grid`` runs every combination. Instead of (or beside) ``vary``, ``cells`` names
each variation and lists its overrides::

    cells:
      open-field: [scene.scenario=open-field, scene.start_m=0]
      640x480: [scene.width=640, scene.height=480]

A cell may also be a mapping ``{set: [overrides], seeds: [0, 1, 2]}``: it runs once per
pipeline seed (``seed=N`` after its overrides), for results that depend on the seed (threshold
mismatch, sensor noise); its rows carry ``repeat`` (and ``seed``), and ``evchain results``
reports the median over the seeds with their range, as for ``repeat`` below::

    cells:
      mismatch-3pct: {set: [emulator.mismatch_sigma=0.03], seeds: [0, 1, 2]}

Several pipelines over the same variations: ``bases`` maps a label to each pipeline (the
table gets a ``base`` column), or to ``{file: PIPELINE, set: [overrides]}`` (one pipeline at two
settings, e.g. frames at 30 and 100 fps; the cells' overrides come after the base's). With
``record`` (a pipeline that runs ``scene`` -> ``emulator``, optionally ``sensor_noise``, and
``aedat_writer``), each variation's events are rendered once, with the overrides that address
the record pipeline's stages, and every base replays them (``evchain run --replay``): two flow
chains over one drive cost one render. ``repeat`` lists override sets applied on top of every
variation, each a separate run (e.g. a drive started a fraction of a metre later): the rows
carry ``repeat`` and ``evchain results`` reports the spread over them.

Each run writes into ``OUT/<hash of the resolved pipeline>/`` (recordings into
``OUT/record-<hash>/``). A run is not repeated when its folder holds an ``ok`` report of the same
run: the same resolved pipeline, the same contents (SHA-256) of every input file it reads (a
recording, a file source's ``path``, DVSFLOW16 ground truth), and the same code (the versions
of evchain, the plugins, Python, numpy and numba, a hash of the source files of evchain that
the run can execute, and of the plugins whose filters it uses): a changed input or a changed
kernel runs again. The evchain files of a run are its filters' modules and the chain runner
with everything they import, read from their sources (``provenance.import_closure``), so a
change to a flow kernel repeats the runs that use it and no recording.

Paths resolve before any work is sent: the sweep's ``base``/``bases``/``record``/``replay``
relative to the sweep file, a pipeline's input files relative to the pipeline file, input files
in the sweep's overrides relative to the sweep file, and ``OUT`` relative to the current folder;
jobs carry them absolute. Runs go to a local process pool, or to a Dask cluster when a scheduler
address is given (``pip install 'evchain[dask]'``); a cluster's workers must see the same files
at the same paths (a shared file system, with ``OUT`` on it). A line is printed as each run
finishes (and a bar over the runs on a terminal). A failed run does not stop the others: its
row says ``failed: <the error's first line>`` in the ``status`` column, and once the table is
written :class:`SweepFailed` names the failed runs (``evchain sweep`` exits with code 2). The
table is written as ``OUT/sweep.csv``, ``OUT/sweep.md`` and ``OUT/sweep.json``
(rows, the machine, wall time).

With ``replay`` (relative to the sweep file, or ``evchain sweep --replay FILE``) every run reads
the recorded events of one earlier ``scene`` -> ``emulator`` run instead of rendering.
"""

from __future__ import annotations

import concurrent.futures
import csv
import hashlib
import io
import itertools
import json
import logging
import os
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evchain.core.config import PipelineSpec, load_pipeline, parse_yaml
from evchain.core.registry import Registry, make_registry
from evchain.errors import ConfigError, EvchainError
from evchain.io.atomic import atomic_write_text

log = logging.getLogger("evchain")

SWEEP_KEYS = {"name", "base", "bases", "mode", "set", "vary", "cells", "report", "description",
              "replay", "record", "repeat"}


@dataclass
class Variation:
    label: str
    overrides: list[str]
    #: pipeline seeds to run the variation with, one run each (None: the pipeline's seed)
    seeds: list[int] | None = None

    @property
    def seed_overrides(self) -> list[list[str]]:
        """One override list per seed run (``[[]]`` without seeds)."""
        return [[]] if self.seeds is None else [[f"seed={s}"] for s in self.seeds]


@dataclass
class SweepSpec:
    name: str
    bases: dict[str, Path]
    variations: list[Variation]
    report: list[str]
    file: str
    replay: Path | None = None
    record: Path | None = None
    repeats: list[list[str]] = field(default_factory=lambda: [[]])
    description: str = ""
    base_sets: dict[str, list[str]] = field(default_factory=dict)
    #: overrides given on the command line (``--set``), already in every variation's overrides
    extra_set: list[str] = field(default_factory=list)

    @property
    def base(self) -> Path:
        """The first (or only) base pipeline."""
        return next(iter(self.bases.values()))

    def repeat_count(self, v: Variation) -> int:
        """How often variation ``v`` runs on each base: every ``repeat`` times every seed."""
        return len(self.repeats) * len(v.seed_overrides)

    @property
    def repeated(self) -> bool:
        """Whether some variation runs more than once (the rows then carry ``repeat``)."""
        return any(self.repeat_count(v) > 1 for v in self.variations)

    def runs(self) -> list[tuple[Variation, int, str, Path]]:
        """Every run: (variation, repeat index, base label, base file)."""
        return [(v, r, label, path) for v in self.variations
                for r in range(self.repeat_count(v)) for label, path in self.bases.items()]

    def overrides(self, v: Variation, repeat: int) -> list[str]:
        """The overrides of run ``repeat`` of ``v``: the variation's, the sweep's repeat,
        then the seed."""
        seeds = v.seed_overrides
        return v.overrides + self.repeats[repeat // len(seeds)] + seeds[repeat % len(seeds)]

    def seed(self, v: Variation, repeat: int) -> int | None:
        """The seed run ``repeat`` of ``v`` sets (None: the pipeline's own)."""
        return None if v.seeds is None else v.seeds[repeat % len(v.seeds)]


def looks_like_sweep(path: str | Path) -> bool:
    """Whether the YAML file at ``path`` is a sweep (``base``/``bases``, no ``chain``)."""
    try:
        data, _ = parse_yaml(Path(path).read_text(encoding="utf-8"), str(path))
    except (OSError, UnicodeDecodeError, ConfigError):
        return False
    return isinstance(data, dict) and "chain" not in data and ("base" in data or "bases" in data)


def load_sweep(path: str | Path, extra_set: Sequence[str] = ()) -> SweepSpec:
    """Read and check a sweep file (errors name file:line:column and the key); ``extra_set``
    (``STAGE.PARAM=VALUE``) is appended to the file's ``set``."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read sweep file: {exc.strerror}", file=str(path)) from None
    data, node = parse_yaml(text, str(path))

    def fail(msg, key=None):
        line = col = None
        if node is not None and key is not None:
            for k, v in node.value:
                if k.value == key:
                    line, col = v.start_mark.line + 1, v.start_mark.column + 1
        raise ConfigError(msg, file=str(path), line=line, column=col, key=key)

    if not isinstance(data, dict):
        fail("a sweep must be a mapping with 'base' and 'vary'")
    for key in data:
        if key not in SWEEP_KEYS:
            fail(f"unknown key; allowed: {', '.join(sorted(SWEEP_KEYS))}", key)
    if ("base" in data) == ("bases" in data) or not ("vary" in data or "cells" in data):
        fail("a sweep needs 'base' (a pipeline file) or 'bases' (LABEL: file), and 'vary' "
             "(KEY: [values]) or 'cells' (LABEL: [overrides])")
    if "bases" in data:
        bases = data["bases"]
        if not isinstance(bases, dict) or not bases or not all(
                isinstance(v, str) or (isinstance(v, dict) and set(v) <= {"file", "set"}
                                       and isinstance(v.get("file"), str)
                                       and isinstance(v.get("set", []), list))
                for v in bases.values()):
            fail("must map a label to each pipeline file, or to {file, set: [overrides]}",
                 "bases")
        base_sets = {str(k): [str(o) for o in v.get("set", [])] for k, v in bases.items()
                     if isinstance(v, dict)}
        bases = {str(k): path.parent / (v if isinstance(v, str) else v["file"])
                 for k, v in bases.items()}
    else:
        if not isinstance(data["base"], str):
            fail("must be a pipeline file", "base")
        bases = {"": path.parent / data["base"]}
        base_sets = {}
    mode = data.get("mode", "one_at_a_time")
    if mode not in ("one_at_a_time", "grid"):
        fail(f"must be 'one_at_a_time' or 'grid', got {mode!r}", "mode")
    common = data.get("set", []) or []
    if not isinstance(common, list):
        fail("must be a list of STAGE.PARAM=VALUE overrides", "set")
    for o in extra_set:
        if "=" not in o or not o.split("=", 1)[0].strip():
            raise ConfigError(f"--set {o!r}: expected STAGE.PARAM=VALUE", file=str(path))
    common = [str(c) for c in common] + list(extra_set)
    variations = []
    if "vary" in data:
        vary = data["vary"]
        if not isinstance(vary, dict) or not vary or not all(
                isinstance(v, list) and v for v in vary.values()):
            fail("must map STAGE.PARAM to a non-empty list of values", "vary")
        variations += _variations(vary, mode, common)
    if "cells" in data:
        cells = data["cells"]
        if not isinstance(cells, dict) or not cells:
            fail("must map a label to a list of STAGE.PARAM=VALUE overrides, or to "
                 "{set: [overrides], seeds: [N, ...]}", "cells")
        variations += [_cell(str(k), v, common, fail) for k, v in cells.items()]
    labels = [v.label for v in variations]
    if len(set(labels)) != len(labels):
        fail(f"two variations share a label: {sorted({x for x in labels if labels.count(x) > 1})}")
    repeats = data.get("repeat", [[]])
    if not isinstance(repeats, list) or not repeats or not all(
            isinstance(r, list) for r in repeats):
        fail("must be a list of override lists, one per repeat (e.g. [[], [scene.start_m=0.5]])",
             "repeat")
    report = data.get("report", []) or []
    for key in ("replay", "record"):
        if data.get(key) is not None and not isinstance(data[key], str):
            fail("must be a file path", key)
    if data.get("replay") is not None and data.get("record") is not None:
        fail("give 'record' (render each variation) or 'replay' (one recording), not both",
             "record")
    return SweepSpec(name=data.get("name") or path.stem, bases=bases, variations=variations,
                     report=list(report), file=str(path),
                     replay=None if data.get("replay") is None else path.parent / data["replay"],
                     record=None if data.get("record") is None else path.parent / data["record"],
                     repeats=[[str(o) for o in r] for r in repeats],
                     description=str(data.get("description") or "").strip(),
                     base_sets=base_sets, extra_set=list(extra_set))


def _cell(label: str, value: Any, common: list[str], fail: Callable) -> Variation:
    """A cell: a list of overrides, or ``{set: [overrides], seeds: [N, ...]}``."""
    if isinstance(value, list):
        return Variation(label, common + [str(o) for o in value])
    if not isinstance(value, dict) or not set(value) <= {"set", "seeds"} or \
            not isinstance(value.get("set", []), list):
        fail(f"cell {label!r} must be a list of STAGE.PARAM=VALUE overrides, or "
             "{set: [overrides], seeds: [N, ...]}", "cells")
    seeds = value.get("seeds")
    if seeds is not None and (
            not isinstance(seeds, list) or not seeds or len(set(map(str, seeds))) != len(seeds)
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                       for s in seeds)):
        fail(f"cell {label!r}: seeds must be a non-empty list of distinct integers >= 0, got "
             f"{seeds!r}", "cells")
    if any(str(o).split("=", 1)[0].strip() == "seed" for o in value.get("set", [])) and seeds:
        fail(f"cell {label!r} sets seed= and seeds: give one of them", "cells")
    return Variation(label, common + [str(o) for o in value.get("set", [])], seeds)


def _overrides(key: str, value: Any) -> list[str]:
    keys = [k.strip() for k in key.split(",")]
    if len(keys) == 1:
        return [f"{key}={json.dumps(value)}"]
    if not isinstance(value, list) or len(value) != len(keys):
        raise ConfigError(f"each value of {key!r} must be a list of {len(keys)} values, got "
                          f"{value!r}", key="vary")
    return [f"{k}={json.dumps(v)}" for k, v in zip(keys, value, strict=True)]


def _variations(vary: dict[str, list], mode: str, common: list[str]) -> list[Variation]:
    if mode == "grid":
        keys = list(vary)
        return [Variation(", ".join(f"{k}={v}" for k, v in zip(keys, combo, strict=True)),
                          common + [o for k, v in zip(keys, combo, strict=True)
                                    for o in _overrides(k, v)])
                for combo in itertools.product(*vary.values())]
    out = []
    for key, values in vary.items():
        out += [Variation(f"{key}={v}", common + _overrides(key, v)) for v in values]
    return out


def config_hash(resolved: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(resolved, sort_keys=True).encode()).hexdigest()[:12]


# -- resolving runs ---------------------------------------------------------------------------

def _stage_names(spec: PipelineSpec) -> set[str]:
    return {n for s in spec.stages for n in (s.use, s.id)}


def _target(override: str) -> str:
    """The stage an override addresses (``seed`` for the pipeline's seed)."""
    key = override.split("=", 1)[0]
    return key if key == "seed" else key.split(".", 1)[0]


def overrides_for(spec: PipelineSpec, overrides: list[str]) -> list[str]:
    """The overrides that address a stage of ``spec`` (and ``seed``): with several bases, an
    override of one flow's stage is not applied to the other flow's pipeline."""
    names = _stage_names(spec) | {"seed"}
    return [o for o in overrides if _target(o) in names]


def events_file(record: PipelineSpec) -> str:
    """The events file a record pipeline writes (its ``aedat_writer``'s path)."""
    writers = [s for s in record.stages if s.use == "aedat_writer"]
    if not writers or [s.use for s in record.stages[:2]] != ["scene", "emulator"]:
        raise ConfigError("a sweep's 'record' pipeline must run scene -> emulator -> "
                          "aedat_writer", file=record.file)
    return writers[0].params.path


@dataclass
class _Job:
    """One pipeline run, every path absolute (a Dask worker may run in any folder): the
    pipeline file, its overrides, the run folder, an optional recording to replay, and the
    folder that relative input files in the overrides are relative to (the sweep file's)."""

    base: str
    overrides: list[str]
    out_dir: str
    replay: str | None = None
    set_dir: str | None = None


def _absolute(path: str | Path) -> str:
    return os.path.abspath(path)


def plan(sweep: SweepSpec, out: Path, registry: Registry,
         check_recordings: bool = True) -> tuple[list[_Job], list[_Job]]:
    """(recording jobs, one job per run of ``sweep.runs()``), every pipeline validated first;
    ``check_recordings``: also that a given ``replay`` recording is this sweep's. Every path
    in the jobs is absolute."""
    out = Path(_absolute(out))
    set_dir = _absolute(Path(sweep.file).parent)
    files = {str(p): _absolute(p)
             for p in [*sweep.bases.values(), *([sweep.record] if sweep.record else [])]}
    plain = {f: load_pipeline(f, registry, set_dir=set_dir) for f in files.values()}
    known = set().union(*(_stage_names(s) for s in plain.values())) | {"seed"}
    for v in sweep.variations:
        for r in range(sweep.repeat_count(v)):
            for o in sweep.overrides(v, r):
                if _target(o) not in known:
                    raise ConfigError(f"{v.label}: override {o!r} addresses no stage of the "
                                      f"sweep's pipelines; stages: {', '.join(sorted(known))}",
                                      file=sweep.file)
    for label, sets in sweep.base_sets.items():
        names = _stage_names(plain[files[str(sweep.bases[label])]]) | {"seed"}
        for o in sets:
            if _target(o) not in names:
                raise ConfigError(f"base {label}: override {o!r} addresses no stage of "
                                  f"{sweep.bases[label]}", file=sweep.file)
    replay = None if sweep.replay is None else _absolute(sweep.replay)
    if replay is not None and not Path(replay).is_file():
        raise ConfigError(f"recording not found: {replay}", file=sweep.file, key="replay")
    record = None if sweep.record is None else files[str(sweep.record)]
    records: dict[str, _Job] = {}
    jobs = []
    for v, r, label, base in sweep.runs():
        base = files[str(base)]
        overrides = sweep.base_sets.get(label, []) + overrides_for(plain[base],
                                                                   sweep.overrides(v, r))
        run_replay = replay
        if record is not None:
            rec_over = overrides_for(plain[record], sweep.overrides(v, r))
            rec = load_pipeline(record, registry, rec_over, set_dir=set_dir)
            rec_dir = out / f"record-{config_hash(rec.resolved())}"
            records.setdefault(str(rec_dir), _Job(record, rec_over, str(rec_dir),
                                                  set_dir=set_dir))
            run_replay = str(rec_dir / events_file(rec))
        spec = load_pipeline(base, registry, overrides, set_dir=set_dir)
        if run_replay is not None:  # a recording still to be made is checked when replayed
            spec = _replayed(spec, run_replay,
                             check_recording=check_recordings and record is None)
        jobs.append(_Job(base, overrides, str(out / config_hash(spec.resolved())), run_replay,
                         set_dir))
    return list(records.values()), jobs


def _replayed(spec: PipelineSpec, replay: str, check_recording: bool = True) -> PipelineSpec:
    from evchain.filters.scene_events import replay_spec

    return replay_spec(spec, replay, check_recording=check_recording)


def validate_sweep(sweep: SweepSpec, registry: Registry | None = None) -> int:
    """Validate every pipeline the sweep would run (no run); returns the number of runs."""
    registry = registry or make_registry()
    records, jobs = plan(sweep, Path("out"), registry, check_recordings=False)
    return len(records) + len(jobs)


def reusable_report(spec: PipelineSpec, registry: Registry,
                    out_dir: Path) -> tuple[dict | None, str | None]:
    """(the report in ``out_dir`` if it is of the same run, else None; why not, if a finished
    run is there). The same run: status ``ok``, the same resolved pipeline, the same contents
    of every input file and the same code (versions, and source hashes of the code it can
    execute)."""
    from evchain.core.chain import versions
    from evchain.provenance import input_digests

    try:
        old = json.loads((out_dir / "report.json").read_text())
    except (OSError, ValueError):
        return None, None
    if old.get("status") != "ok" or old.get("pipeline") != spec.resolved():
        return None, None
    if old.get("inputs") != input_digests(spec):
        return None, "an input file changed"
    if old.get("versions") != versions(registry, spec):
        return None, "the code changed"
    return old, None


def _run_one(job: _Job, registry: Registry | None = None) -> dict[str, Any]:
    """Run ``job`` unless its folder holds the same run. A failed run does not raise: it is
    ``{"report": None, "error": MESSAGE}``, a row of the table. ``again``: why a finished run
    in the folder was not reused."""
    from evchain.core.chain import run_pipeline

    try:
        registry = registry or make_registry()
        spec = load_pipeline(job.base, registry, job.overrides, set_dir=job.set_dir)
        if job.replay is not None:
            spec = _replayed(spec, job.replay)
        old, again = reusable_report(spec, registry, Path(job.out_dir))
        if old is not None:
            return {"report": old, "cached": True, "error": None}
        return {"report": run_pipeline(spec, registry, job.out_dir).report, "cached": False,
                "error": None, "again": again}
    except Exception as exc:  # noqa: BLE001 - every failure becomes the run's row
        text = str(exc) if isinstance(exc, EvchainError) else f"{type(exc).__name__}: {exc}"
        return {"report": None, "cached": False, "error": text}


def _run_all(jobs: list[_Job], workers: int, scheduler: str | None,
             registry: Registry | None,
             on_done: Callable[[int, dict[str, Any]], object]) -> list[dict[str, Any]]:
    """Every job's outcome, in job order; ``on_done(index, outcome)`` as each finishes."""
    results: list[dict[str, Any]] = [{}] * len(jobs)

    def done(i: int, get: Callable[[], dict[str, Any]]) -> None:
        try:
            results[i] = get()
        except Exception as exc:  # noqa: BLE001 - a lost worker fails its run, not the sweep
            results[i] = {"report": None, "cached": False,
                          "error": f"{type(exc).__name__}: {exc}"}
        on_done(i, results[i])

    if not jobs:
        return results
    if scheduler is None and workers <= 1:
        for i, job in enumerate(jobs):
            done(i, lambda job=job: _run_one(job, registry))
        return results
    if scheduler is not None:
        try:
            from dask.distributed import Client, as_completed
        except ImportError:
            raise ConfigError("a Dask scheduler needs 'pip install evchain[dask]'",
                              file="--scheduler") from None
        try:
            client = Client(scheduler, timeout=30)
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"cannot reach the Dask scheduler at {scheduler}: {exc}",
                              file="--scheduler") from None
        with client:
            futures = [client.submit(_run_one, job, pure=False) for job in jobs]
            index = {f.key: i for i, f in enumerate(futures)}
            for future in as_completed(futures):
                done(index[future.key], future.result)
        return results
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(_run_one, job): i for i, job in enumerate(jobs)}
        for future in concurrent.futures.as_completed(futures):
            done(futures[future], future.result)
    return results


#: report keys read from the run's report rather than its metrics (``cpu.cpu_s_per_simulated_s``)
RUN_KEYS = ("cpu",)


def lookup(report: dict[str, Any], dotted: str):
    """A report key's value: a metric (``foe.dx_mean_px``) or, for ``cpu.*``, the run's CPU
    time after the sensor; None if the run has none."""
    value: Any = report.get("metrics", {})
    if dotted.split(".", 1)[0] in RUN_KEYS and dotted.split(".", 1)[0] not in value:
        value = report
    for part in dotted.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return value


class SweepFailed(EvchainError):
    """Some runs of a sweep failed (the table was still written; it marks them)."""


class _Progress:
    """One line per finished run, and a bar over the runs on a terminal."""

    def __init__(self, total: int, echo: Callable[[str], object]):
        from tqdm import tqdm

        self.echo, self.total, self.done = echo, total, 0
        self.bar = tqdm(total=total, unit="run", desc="sweep", leave=False, file=sys.stderr,
                        dynamic_ncols=True, disable=None)

    def line(self, text: str) -> None:
        self.done += 1
        self.bar.clear()
        self.echo(f"  [{self.done}/{self.total}] {text}")
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0] if text.strip() else text


def run_sweep(sweep: SweepSpec, out_dir: str | Path, workers: int = 2,
              scheduler: str | None = None, registry: Registry | None = None,
              echo: Callable[[str], object] = print) -> list[dict[str, Any]]:
    """Run every variation (skipping those whose folder holds the same run) and return one
    table row per run, printing a line as each run finishes. The table is written even when
    runs fail; then :class:`SweepFailed` names them."""
    from evchain.machine import machine_info

    out = Path(_absolute(out_dir))
    started = time.perf_counter()
    load_before = machine_info()["load"]
    records, jobs = plan(sweep, out, registry or make_registry())  # fails before any run
    runs = sweep.runs()
    multi = len(sweep.bases) > 1 or next(iter(sweep.bases)) != ""
    progress = _Progress(len(records) + len(jobs), echo)
    try:
        failed_records: dict[str, str] = {}
        if records:
            echo(f"  recording {len(records)} drives")

            def recorded(i: int, outcome: dict[str, Any]) -> None:
                name = Path(records[i].out_dir).name
                if outcome["error"]:
                    failed_records[records[i].out_dir] = outcome["error"]
                    progress.line(f"{name} FAILED: {_first_line(outcome['error'])}")
                else:
                    again = f" (run again: {outcome['again']})" if outcome.get("again") else ""
                    progress.line(f"{name} {'(cached)' if outcome['cached'] else 'recorded'}"
                                  f"{again}")

            _run_all(records, workers, scheduler, registry, recorded)
        outcomes: list[dict[str, Any]] = []
        todo = []
        for i, job in enumerate(jobs):
            error = failed_records.get(str(Path(job.replay).parent)) if job.replay else None
            outcomes.append({"report": None, "cached": False,
                             "error": f"its recording failed: {_first_line(error)}"}
                            if error else {})
            if error:
                progress.line(f"{runs[i][0].label:28s} {runs[i][2]:6s} FAILED: "
                              f"{outcomes[i]['error']}")
            else:
                todo.append(i)

        def finished(k: int, outcome: dict[str, Any]) -> None:
            i = todo[k]
            outcomes[i] = outcome
            v, r, label, _ = runs[i]
            seed = sweep.seed(v, r)
            label += "" if seed is None else f" seed {seed}"
            what = (f"FAILED: {_first_line(outcome['error'])}" if outcome["error"] else
                    ("(cached) " if outcome["cached"] else "") +
                    (f"(run again: {outcome['again']}) " if outcome.get("again") else "") +
                    " ".join(f"{key}={_fmt(lookup(outcome['report'], key))}"
                             for key in sweep.report))
            progress.line(f"{v.label:28s} {label:6s} {what}")

        _run_all([jobs[i] for i in todo], workers, scheduler, registry, finished)
    finally:
        progress.close()
    rows = []
    seeded = any(v.seeds is not None for v in sweep.variations)
    for (v, r, label, _), job, outcome in zip(runs, jobs, outcomes, strict=True):
        report = outcome["report"] or {}
        row: dict[str, Any] = {"variation": v.label}
        if multi:
            row["base"] = label
        if sweep.repeated:
            row["repeat"] = r
        if seeded:
            row["seed"] = sweep.seed(v, r)
        row.update({"run": Path(job.out_dir).name,
                    "status": "ok" if report else f"failed: {_first_line(outcome['error'])}",
                    "cached": outcome["cached"],
                    "wall_s": round(report["wall_s"], 3) if report else None})
        row.update({key: lookup(report, key) if report else None for key in sweep.report})
        rows.append(row)
    cached = sum(1 for o in outcomes if o["cached"])
    if cached:
        log.info("%d of %d runs taken from %s (same pipeline, input files and code)", cached,
                 len(outcomes), out)
    write_table(rows, out)
    machine = machine_info()
    machine["load_before"] = load_before
    summary = {"sweep": sweep.name, "file": Path(sweep.file).as_posix(),
               "description": sweep.description, "extra_set": sweep.extra_set,
               "report": sweep.report,
               "bases": {k: Path(p).as_posix() for k, p in sweep.bases.items()},
               "wall_s": round(time.perf_counter() - started, 1), "machine": machine,
               "rows": rows}
    atomic_write_text(out / "sweep.json", json.dumps(summary, indent=2))
    failed = [(row, r) for row, r in zip(rows, runs, strict=True) if row["status"] != "ok"]
    if failed:
        names = [row["variation"] + (f" ({row['base']})" if multi else "") +
                 (f" repeat {row['repeat']}" if "repeat" in row else "") +
                 (f" seed {row['seed']}" if row.get("seed") is not None else "") +
                 f" [{row['run']}]"
                 for row, _ in failed]
        raise SweepFailed(f"{len(failed)} of {len(rows)} runs failed: {'; '.join(names)}; the "
                          f"table ({out / 'sweep.md'}) marks them, and each run folder's "
                          "report.json has the error")
    return rows


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def write_table(rows: list[dict[str, Any]], out: Path) -> None:
    cols = list(rows[0]) if rows else []
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")  # quotes labels of joint keys (commas)
    writer.writerow(cols)
    writer.writerows([r[c] for c in cols] for r in rows)
    md = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(_fmt(r[c]) for c in cols) + " |" for r in rows]
    atomic_write_text(out / "sweep.csv", text.getvalue())
    atomic_write_text(out / "sweep.md", "\n".join(md) + "\n")
