"""``evchain sweep``: variations of a base pipeline, run in parallel, cached, tabulated.

A sweep file::

    name: threshold                     # optional, defaults to the file's stem
    base: ../reference-lk.yaml          # relative to the sweep file
    mode: one_at_a_time                 # or: grid (every combination)
    set: [scene.duration_s=6]           # overrides applied to every run (optional)
    vary:
      scene.speed_mps: [10, 20, 30]
      emulator.threshold_on,emulator.threshold_off: [[10, 10], [20, 20], [40, 40]]
    report: [foe.dx_mean_px, foe.dy_mean_px, ttc.median_rel_error_last3s]
    replay: ../../runs/reference/events.aedat   # optional: see below

A key naming several parameters, separated by commas, sets them together from a list per value.
``one_at_a_time`` varies one key while the others keep the base's values (as the thesis's
tables do); ``grid`` runs every combination. Each run writes into
``OUT/<hash of the resolved pipeline>/``; a run whose folder already holds an ``ok`` report of
the same resolved pipeline is not repeated. Runs go to a local process pool, or to a Dask cluster
when a scheduler address is given (``pip install 'evchain[dask]'``). The table is printed and
written as ``OUT/sweep.csv`` and ``OUT/sweep.md``.

With ``replay`` (relative to the sweep file, or ``evchain sweep --replay FILE``) every run reads
the recorded events of an earlier ``scene`` -> ``emulator`` run instead of rendering (see
``evchain run --replay``), so sweeps over the later stages take seconds per run.
"""

from __future__ import annotations

import csv
import hashlib
import io
import itertools
import json
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evchain.core.config import load_pipeline, parse_yaml
from evchain.core.registry import Registry, make_registry
from evchain.errors import ConfigError
from evchain.io.atomic import atomic_write_text

SWEEP_KEYS = {"name", "base", "mode", "set", "vary", "report", "description", "replay"}


@dataclass
class Variation:
    label: str
    overrides: list[str]


@dataclass
class SweepSpec:
    name: str
    base: Path
    variations: list[Variation]
    report: list[str]
    file: str
    replay: Path | None = None


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep file (errors name file:line:column and the key)."""
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
    if "base" not in data or "vary" not in data:
        fail("a sweep needs 'base' (a pipeline file) and 'vary' (KEY: [values])")
    vary = data["vary"]
    if not isinstance(vary, dict) or not vary or not all(
            isinstance(v, list) and v for v in vary.values()):
        fail("must map STAGE.PARAM to a non-empty list of values", "vary")
    mode = data.get("mode", "one_at_a_time")
    if mode not in ("one_at_a_time", "grid"):
        fail(f"must be 'one_at_a_time' or 'grid', got {mode!r}", "mode")
    common = data.get("set", []) or []
    if not isinstance(common, list):
        fail("must be a list of STAGE.PARAM=VALUE overrides", "set")
    report = data.get("report", []) or []
    replay = data.get("replay")
    if replay is not None and not isinstance(replay, str):
        fail("must be the path of a recorded run's events file", "replay")
    return SweepSpec(name=data.get("name") or path.stem, base=path.parent / data["base"],
                     variations=_variations(vary, mode, [str(c) for c in common]),
                     report=list(report), file=str(path),
                     replay=None if replay is None else path.parent / replay)


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


def _load(base: str, overrides: list[str], registry: Registry, replay: str | None):
    spec = load_pipeline(base, registry, overrides)
    if replay is None:
        return spec
    from evchain.filters.scene_events import replay_spec

    return replay_spec(spec, replay)


def _run_one(base: str, overrides: list[str], out_dir: str, registry: Registry | None = None,
             replay: str | None = None):
    from evchain.core.chain import run_pipeline

    registry = registry or make_registry()
    spec = _load(base, overrides, registry, replay)
    report_path = Path(out_dir) / "report.json"
    if report_path.exists():
        old = json.loads(report_path.read_text())
        if old.get("status") == "ok" and old.get("pipeline") == spec.resolved():
            return old, True
    return run_pipeline(spec, registry, out_dir).report, False


def lookup(report: dict[str, Any], dotted: str):
    value: Any = report.get("metrics", {})
    for part in dotted.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return value


def run_sweep(sweep: SweepSpec, out_dir: str | Path, workers: int = 2,
              scheduler: str | None = None, registry: Registry | None = None,
              echo=print) -> list[dict[str, Any]]:
    """Run every variation (skipping cached ones) and return one table row per variation."""
    out = Path(out_dir)
    check = registry or make_registry()
    replay = None if sweep.replay is None else str(sweep.replay)
    jobs = []
    for v in sweep.variations:
        spec = _load(str(sweep.base), v.overrides, check, replay)  # fail early, before any run
        jobs.append((v, str(out / config_hash(spec.resolved()))))
    if scheduler is None and workers <= 1:
        results = [_run_one(str(sweep.base), v.overrides, d, registry, replay) for v, d in jobs]
    elif scheduler is not None:
        try:
            from dask.distributed import Client
        except ImportError:
            raise ConfigError("a Dask scheduler needs 'pip install evchain[dask]'",
                              file="--scheduler") from None
        with Client(scheduler) as client:
            futures = [client.submit(_run_one, str(sweep.base), v.overrides, d, None, replay,
                                     pure=False) for v, d in jobs]
            results = client.gather(futures)
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(_run_one, str(sweep.base), v.overrides, d, None, replay)
                       for v, d in jobs]
            results = [f.result() for f in futures]
    rows = []
    for (v, d), (report, cached) in zip(jobs, results, strict=True):
        row = {"variation": v.label, "run": Path(d).name, "cached": cached,
               "wall_s": round(report["wall_s"], 3)}
        row.update({key: lookup(report, key) for key in sweep.report})
        rows.append(row)
        echo(f"  {v.label:40s} {'(cached) ' if cached else ''}" +
             " ".join(f"{k}={_fmt(row[k])}" for k in sweep.report))
    write_table(rows, out)
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

