"""``evchain results``: every claimed number from one command, with its spread and a verdict.

``results/results.yaml`` (the manifest) lists what is measured: sweeps (``sweeps: {NAME:
FILE}``), benchmark rows (``bench: [{prefix, repeat, quick}]``; a workload belongs to the longest
prefix it starts with), how metrics read
(``metrics: {KEY: {label, better, format}}``) and the goals (``goals: [...]``).

* ``evchain results --run [NAME ...]`` runs the listed sweeps and benchmarks (all, or those
  named) and saves what they gave as JSON under ``results/`` (``sweeps/NAME.json``,
  ``bench/PREFIX.json``), with the machine it ran on.
* ``evchain results`` writes ``docs/results.md`` from the saved JSON alone (nothing is run);
  ``--check`` exits 1 when the file differs from what the saved results give.

A value is the median over its repeats (a sweep's ``repeat`` runs or a cell's ``seeds``, or a
benchmark run ``repeat`` times); its spread is max - min over them. The evaluation summary's
per-cell value is that median, so a cell run over seeds enters it once. A goal's margin is
how far the value is on the good side of the goal. Verdict: ``met`` when every repeat meets the
goal and the margin exceeds the spread, ``not met`` when no repeat meets it, else
``borderline``; a value measured fewer than three times gets ``unrepeated`` instead of a
verdict.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evchain.core.config import parse_yaml
from evchain.errors import ConfigError
from evchain.io.atomic import atomic_write_text

MANIFEST = Path("results") / "results.yaml"
OUTPUT = Path("docs") / "results.md"
MIN_REPEATS = 3
MANIFEST_KEYS = {"sweeps", "bench", "metrics", "goals", "evaluation", "comparison"}
GOAL_KEYS = {"name", "source", "select", "metric", "goal"}


# -- the manifest ------------------------------------------------------------------------------

@dataclass
class Goal:
    name: str
    source: str            # "sweep:NAME" or "bench"
    select: dict[str, Any]  # row fields that pick the rows (e.g. base: lk; workload: ...)
    metric: str            # a row field (sweep: the report key; bench: throughput, error, ...)
    op: str                # "<=" or ">="
    target: float


@dataclass
class Manifest:
    root: Path
    sweeps: dict[str, Path]
    titles: dict[str, str]
    bench: list[dict[str, Any]]
    metrics: dict[str, dict[str, Any]]
    goals: list[Goal]
    evaluation: dict[str, Any]
    comparison: dict[str, Any] | None = None

    def results_dir(self) -> Path:
        return self.root / "results"


def load_manifest(root: Path = Path(".")) -> Manifest:
    """Read ``results/results.yaml`` under ``root`` (errors name the file, line and key)."""
    path = root / MANIFEST
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read the results manifest ({exc.strerror}); run evchain "
                          "results from the repository's top folder", file=str(path)) from None
    data, node = parse_yaml(text, str(path))

    def fail(msg, key=None, line=None):
        raise ConfigError(msg, file=str(path), key=key, line=line)

    if not isinstance(data, dict):
        fail("must be a mapping with sweeps, bench, metrics and goals")
    for key in data:
        if key not in MANIFEST_KEYS:
            fail(f"unknown key; allowed: {', '.join(sorted(MANIFEST_KEYS))}", key)
    sweeps = data.get("sweeps") or {}
    if not isinstance(sweeps, dict) or not all(
            isinstance(v, str) or (isinstance(v, dict) and isinstance(v.get("file"), str))
            for v in sweeps.values()):
        fail("must map a name to a sweep file, or to {file, title}", "sweeps")
    titles = {k: v.get("title", k) if isinstance(v, dict) else k for k, v in sweeps.items()}
    sweeps = {k: v["file"] if isinstance(v, dict) else v for k, v in sweeps.items()}
    bench = data.get("bench") or []
    if not isinstance(bench, list) or not all(isinstance(b, dict) and "prefix" in b
                                              for b in bench):
        fail("must be a list of {prefix, repeat, quick}", "bench")
    goals = []
    goal_nodes = _list_nodes(node, "goals")
    for i, g in enumerate(data.get("goals") or []):
        line = goal_nodes[i].start_mark.line + 1 if i < len(goal_nodes) else None
        if not isinstance(g, dict) or set(g) - GOAL_KEYS or {"name", "source", "metric",
                                                              "goal"} - set(g):
            fail(f"a goal has the keys {', '.join(sorted(GOAL_KEYS))} (select optional)",
                 "goals", line)
        op, _, num = str(g["goal"]).strip().partition(" ")
        try:
            target = float(num)
        except ValueError:
            target = math.nan
        if op not in ("<=", ">=") or not math.isfinite(target):
            fail(f"goal {g['goal']!r} must read '<= NUMBER' or '>= NUMBER'", "goals", line)
        src = str(g["source"])
        if src != "bench" and not (src.startswith("sweep:") and src[6:] in sweeps):
            fail(f"source {src!r} must be 'bench' or 'sweep:NAME' of a listed sweep", "goals",
                 line)
        goals.append(Goal(str(g["name"]), src, dict(g.get("select") or {}), str(g["metric"]),
                          op, target))
    comparison = data.get("comparison")
    if comparison is not None:
        chains = comparison.get("chains") if isinstance(comparison, dict) else None
        if not isinstance(chains, list) or not chains or not all(
                isinstance(c, dict) and {"label", "sweep", "base"} <= set(c)
                and c["sweep"] in sweeps for c in chains):
            fail("must hold chains: [{label, sweep, base}] of listed sweeps, and metrics",
                 "comparison")
    return Manifest(root=root, sweeps={k: root / v for k, v in sweeps.items()}, titles=titles,
                    bench=bench,
                    metrics=dict(data.get("metrics") or {}), goals=goals,
                    evaluation=dict(data.get("evaluation") or {}),
                    comparison=dict(comparison) if comparison else None)


def _list_nodes(node, key: str) -> list:
    if node is None:
        return []
    for k, v in node.value:
        if k.value == key and hasattr(v, "value") and isinstance(v.value, list):
            return v.value
    return []


# -- running and saving ------------------------------------------------------------------------

def bench_file(m: Manifest, prefix: str) -> Path:
    return m.results_dir() / "bench" / f"{prefix}.json"


def sweep_file(m: Manifest, name: str) -> Path:
    return m.results_dir() / "sweeps" / f"{name}.json"


def run_and_save(m: Manifest, names: list[str], workers: int = 2,
                 echo: Callable[[str], object] = print) -> list[Path]:
    """Run the manifest's sweeps and benchmarks (those in ``names``, or all) and save them."""
    from evchain import bench
    from evchain.core.registry import make_registry
    from evchain.machine import machine_info
    from evchain.sweep import load_sweep, run_sweep

    known = list(m.sweeps) + [b["prefix"] for b in m.bench]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ConfigError(f"{', '.join(unknown)}: not in the manifest; known: "
                          f"{', '.join(known)}", file=str(m.root / MANIFEST))
    saved = []
    for name, path in m.sweeps.items():
        if names and name not in names:
            continue
        out = m.root / "out" / "sweeps" / name
        echo(f"sweep {name} ({path})")
        run_sweep(load_sweep(path), out, workers=workers, echo=echo)
        target = sweep_file(m, name)
        target.parent.mkdir(parents=True, exist_ok=True)
        summary = json.loads((out / "sweep.json").read_text())
        summary["command"] = f"evchain results --run {name}"
        atomic_write_text(target, json.dumps(summary, indent=2) + "\n")
        saved.append(target)
    registry = make_registry()
    for entry in m.bench:
        prefix = entry["prefix"]
        if names and prefix not in names:
            continue
        quick = bool(entry.get("quick", False))
        repeat = int(entry.get("repeat", MIN_REPEATS))
        workloads = own_workloads(m, prefix, bench.select(registry.workloads, [prefix]))
        if not workloads:
            raise ConfigError(f"no benchmark workload starts with {prefix!r}",
                              file=str(m.root / MANIFEST), key="bench")
        echo(f"bench {prefix} x {repeat}{' --quick' if quick else ''}")
        bench.prepare(workloads, quick=quick, echo=echo)   # rendered inputs, not timed
        machine = machine_info()
        t0 = time.perf_counter()
        rows = [row.as_dict() for row in bench.run(workloads, quick=quick, repeat=repeat,
                                                    echo=echo)]
        machine["load_after"] = machine_info()["load"]
        doc = {"prefix": prefix, "quick": quick, "repeat": repeat,
               "command": f"evchain results --run {prefix}", "machine": machine,
               "wall_s": round(time.perf_counter() - t0, 1), "rows": rows}
        target = bench_file(m, prefix)
        atomic_write_text(target, json.dumps(doc, indent=2, default=_json_default) + "\n")
        saved.append(target)
    return saved


def own_workloads(m: Manifest, prefix: str, workloads: dict[str, Callable]
                  ) -> dict[str, Callable]:
    """The ``workloads`` (named ``prefix``...) that belong to the manifest's entry ``prefix``:
    a workload belongs to the longest prefix of the manifest it starts with (``emulator-``
    leaves ``emulator-peer-*`` to ``emulator-peer``), so no row is measured twice or counted in
    two files."""
    longer = [b["prefix"] for b in m.bench
              if len(b["prefix"]) > len(prefix) and b["prefix"].startswith(prefix)]
    return {k: v for k, v in workloads.items() if not any(k.startswith(p) for p in longer)}


def _json_default(v):
    if hasattr(v, "item"):
        return v.item()
    if hasattr(v, "tolist"):
        return v.tolist()
    return str(v)


# -- values, spread, verdicts ------------------------------------------------------------------

@dataclass
class Value:
    values: list[float]

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def median(self) -> float | None:
        return statistics.median(self.values) if self.values else None

    @property
    def spread(self) -> float | None:
        return max(self.values) - min(self.values) if self.values else None


def verdict(v: Value, op: str, target: float) -> tuple[float | None, str]:
    """(margin, verdict) of value ``v`` against the goal ``op target``: ``met`` when every
    repeat meets the goal and the median's margin exceeds the spread, ``not met`` when no
    repeat meets it, ``borderline`` otherwise."""
    if v.median is None:
        return None, "no data"
    margin = (target - v.median) if op == "<=" else (v.median - target)
    if v.n < MIN_REPEATS:
        return margin, "unrepeated"
    meets = [(x <= target) if op == "<=" else (x >= target) for x in v.values]
    if all(meets) and margin > v.spread:
        return margin, "met"
    if not any(meets):
        return margin, "not met"
    return margin, "borderline"


def _number(x) -> float | None:
    if isinstance(x, bool) or x is None:
        return None
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def collect(rows: list[dict[str, Any]], select: dict[str, Any], metric: str) -> Value:
    """The values of ``metric`` over the rows matching ``select`` (one per repeat)."""
    vals = [_number(r.get(metric)) for r in rows
            if all(str(r.get(k)) == str(v) for k, v in select.items())]
    return Value([v for v in vals if v is not None])


# -- the page --------------------------------------------------------------------------------------

def _cell(text: object) -> str:
    """Text for a markdown table cell (a literal | would end the cell)."""
    return str(text).replace("|", "\\|")


def _fmt(v: float | None, spec: str = ".3g") -> str:
    if v is None:
        return "-"
    if spec.endswith("%"):
        return format(v, spec)
    a = abs(v)
    if a >= 1e5:
        return f"{v / 1e6:.3g} M"
    if a >= 1e3:
        return f"{v:.0f}"
    return format(v, spec)


def _value_text(v: Value, spec: str) -> str:
    if v.median is None:
        return "-"
    if v.n == 1 or v.spread == 0:
        return _fmt(v.median, spec) + ("" if v.n == 1 else f" (x{v.n}, equal)")
    return f"{_fmt(v.median, spec)} ({_fmt(min(v.values), spec)}-{_fmt(max(v.values), spec)}, " \
           f"x{v.n})"


def _machine_text(mach: dict[str, Any] | None) -> str:
    if not mach:
        return "machine not recorded"
    load = mach.get("load")
    parts = [f"{mach.get('cores')} cores", str(mach.get("cpu")),
             f"load {load:.1f}" if isinstance(load, int | float) else None,
             (f"evchain {mach['evchain']}" if mach.get("evchain") else None),
             (f"commit {mach['commit']}" if mach.get("commit") else None)]
    return ", ".join(p for p in parts if p)


def _load(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ConfigError(f"not valid JSON: {exc.msg}", file=str(path), line=exc.lineno) \
            from None


class _Sources:
    """The saved results, read once."""

    def __init__(self, m: Manifest):
        self.sweeps = {name: _load(sweep_file(m, name)) for name in m.sweeps}
        self.bench = {b["prefix"]: _load(bench_file(m, b["prefix"])) for b in m.bench}

    def rows(self, source: str) -> tuple[list[dict[str, Any]], dict | None]:
        if source == "bench":
            rows, mach = [], None
            for doc in self.bench.values():
                if doc:
                    rows += doc["rows"]
                    mach = mach or doc.get("machine")
            return rows, mach
        doc = self.sweeps.get(source.removeprefix("sweep:"))
        return (doc["rows"], doc.get("machine")) if doc else ([], None)

    def command(self, goal: Goal) -> str:
        if goal.source != "bench":
            return f"evchain results --run {goal.source.removeprefix('sweep:')}"
        wl = str(goal.select.get("workload", ""))
        hits = [p for p in self.bench if wl.startswith(p)]
        return f"evchain results --run {max(hits, key=len)}" if hits else "evchain bench"


def render(m: Manifest) -> str:
    """docs/results.md from the saved results (deterministic: nothing is measured here)."""
    src = _Sources(m)
    out = ["# Results", "",
           "Generated by `evchain results` from the saved measurements in `results/` (do not "
           "edit by hand). `evchain results --run [NAME ...]` measures again and saves; "
           "`evchain results` rewrites this page; `evchain results --check` tells whether it "
           "is current. A value is the median over its repeats, with the range (min-max) and "
           "the number of repeats in brackets. Verdicts: **met** when every repeat meets the "
           "goal and the median's margin exceeds the spread of the repeats, **not met** when no "
           "repeat meets it, **borderline** otherwise; values measured fewer than "
           f"{MIN_REPEATS} times are **unrepeated**.", ""]
    out += _goals_section(m, src)
    out += _sweep_sections(m, src)
    out += _evaluation_section(m, src)
    out += _comparison_section(m, src)
    out += _bench_section(m, src)
    return "\n".join(out).rstrip() + "\n"


def _metric_meta(m: Manifest, key: str) -> dict[str, Any]:
    meta = dict(m.metrics.get(key) or {})
    meta["label"] = _cell(meta.get("label", key))
    meta.setdefault("format", ".3g")
    meta.setdefault("better", "lower")
    return meta


def _goals_section(m: Manifest, src: _Sources) -> list[str]:
    if not m.goals:
        return []
    out = ["## Goals", "",
           "| goal | measured on | value | goal | margin | verdict | reproduce |",
           "|---|---|---|---|---|---|---|"]
    for g in m.goals:
        rows, _ = src.rows(g.source)
        v = collect(rows, g.select, g.metric)
        margin, word = verdict(v, g.op, g.target)
        spec = _metric_meta(m, g.metric)["format"]
        data = _data_of(rows, g.select, g.source)
        out.append(f"| {_cell(g.name)} | {_cell(data)} | {_value_text(v, spec)} | "
                   f"{g.op} {_fmt(g.target, spec)} | {_fmt(margin, spec)} | {word} | "
                   f"`{src.command(g)}` |")
    return out + [""]


def _data_of(rows: list[dict[str, Any]], select: dict[str, Any], source: str) -> str:
    hit = next((r for r in rows if all(str(r.get(k)) == str(v) for k, v in select.items())),
               None)
    if source != "bench":
        sel = ", ".join(f"{k} {v}" for k, v in select.items())
        return f"sweep {source.removeprefix('sweep:')}" + (f" ({sel})" if sel else "")
    if hit is None:
        return str(select.get("workload", "-"))
    data = hit.get("data") or hit.get("scene") or "-"
    return f"{hit.get('workload')}: {data}"


def _sweep_table(m: Manifest, rows: list[dict[str, Any]], keys: list[str],
                 variations: list[str] | None = None) -> list[str]:
    bases = list(dict.fromkeys(r.get("base", "") for r in rows))
    variations = variations or list(dict.fromkeys(r["variation"] for r in rows))
    head = ["cell", "flow"] + [_metric_meta(m, k)["label"] for k in keys]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for var in variations:
        for b in bases:
            cells = [var, b or "-"]
            for k in keys:
                v = collect(rows, {"variation": var, "base": b} if b else {"variation": var}, k)
                cells.append(_value_text(v, _metric_meta(m, k)["format"]))
            out.append("| " + " | ".join(cells) + " |")
    return out


def _sweep_sections(m: Manifest, src: _Sources) -> list[str]:
    """One section per sweep other than the evaluation set's."""
    out = []
    for name in m.sweeps:
        if name == m.evaluation.get("sweep") or name in _comparison_only(m):
            continue
        doc = src.sweeps.get(name)
        out += [f"## {m.titles[name]}", ""]
        if not doc:
            out += [f"Not measured yet: `evchain results --run {name}`.", ""]
            continue
        out += [doc.get("description", ""), "",
                f"Sweep `{doc['file']}`; {doc['wall_s']:g} s wall on "
                f"{_machine_text(doc.get('machine'))}. Reproduce: `{doc['command']}`.", ""]
        out += _sweep_table(m, doc["rows"], doc["report"]) + [""]
    return out


def _evaluation_section(m: Manifest, src: _Sources) -> list[str]:
    cfg = m.evaluation
    name = cfg.get("sweep")
    if not name:
        return []
    doc = src.sweeps.get(name)
    out = ["## Evaluation set", ""]
    if not doc:
        return out + [f"Not measured yet: `evchain results --run {name}`.", ""]
    ref = cfg.get("reference_cell")
    keys = list(cfg.get("summary") or doc["report"])
    rows = doc["rows"]
    cells = [v for v in dict.fromkeys(r["variation"] for r in rows) if v != ref]
    starts = _starts(rows)
    n_starts = len(set(starts))
    by_start = [[r for r, st in zip(rows, starts, strict=True) if st == i]
                for i in sorted(set(starts))]
    each = _renders_text(rows, n_starts)
    out += [doc.get("description", ""), "",
            f"Sweep `{doc['file']}`: {len(cells)} cells, {each}; {doc['wall_s']:g} s wall on "
            f"{_machine_text(doc.get('machine'))}. Reproduce: `{doc['command']}`.", "",
            "### Summary", "",
            "Median and worst over the evaluation cells (the reference cell, from the tuning "
            "set, beside them; a metric a cell does not define, such as TTC without an "
            "obstacle, is left out of that cell).", ""]
    bases = list(dict.fromkeys(r.get("base", "") for r in rows))
    if n_starts > 1:
        out += [f"In brackets: the range of the same value over the {n_starts} starts (each "
                "cell's runs of one start only; over seeds, their median), the run-to-run "
                "spread against which a goal's margin is judged.", ""]
    head = ["metric"] + [f"{b}: {col}" for b in bases for col in ("reference", "median",
                                                                  "worst (cell)")]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k in keys:
        meta = _metric_meta(m, k)
        fmt = meta["format"]
        cells_txt = [meta["label"]]
        for b in bases:
            sel = {"base": b} if b else {}
            r = collect(rows, {**sel, "variation": ref}, k) if ref else Value([])
            med, worst = _median_and_worst(rows, sel, cells, k, meta["better"])
            spans = ["", ""]
            if n_starts > 1 and worst:
                per_start = [_median_and_worst(these, sel, cells, k, meta["better"])
                             for these in by_start]
                for j, vals in enumerate(([e[0] for e in per_start],
                                          [e[1][1] for e in per_start if e[1]])):
                    spans[j] = f"{_fmt(min(vals), fmt)}-{_fmt(max(vals), fmt)}"
            cells_txt += [_fmt(r.median, fmt),
                          _fmt(med, fmt) + (f" ({spans[0]})" if spans[0] else ""),
                          f"{_fmt(worst[1], fmt)} ({worst[0]}{'; ' + spans[1] if spans[1] else ''})"
                          if worst else "-"]
        out.append("| " + " | ".join(cells_txt) + " |")
    out += ["", "### Every cell", ""]
    return out + _sweep_table(m, rows, doc["report"], ([ref] if ref else []) + cells) + [""]


def _median_and_worst(rows: list[dict[str, Any]], sel: dict[str, Any], cells: list[str],
                      metric: str, better: str | None
                      ) -> tuple[float | None, tuple[str, float] | None]:
    """The median over ``cells`` of each cell's median of ``metric`` in ``rows`` (matching
    ``sel``), and the worst cell with its value (cells without the metric left out)."""
    per = [(c, collect(rows, {**sel, "variation": c}, metric).median) for c in cells]
    per = [(c, v) for c, v in per if v is not None]
    if not per:
        return None, None
    worst = (max if better == "lower" else min)(per, key=lambda cv: cv[1])
    return statistics.median([v for _, v in per]), worst


def _starts(rows: list[dict[str, Any]]) -> list[int]:
    """Each row's start: the index of the sweep's repeat it ran with. A cell over seeds runs
    every seed at every start, its run ``repeat`` = start x seeds + the seed's place
    (:meth:`evchain.sweep.SweepSpec.overrides`)."""
    seeds: dict[tuple[str, str], set] = {}
    for r in rows:
        seeds.setdefault((r["variation"], r.get("base", "")), set()).add(r.get("seed"))
    return [int(r.get("repeat") or 0) // len(seeds[(r["variation"], r.get("base", ""))])
            for r in rows]


def _renders_text(rows: list[dict[str, Any]], n_starts: int) -> str:
    """How often each cell was rendered and replayed: once per start, and once per seed and
    start for a cell over seeds (its value then the median over its runs)."""
    seeded = _seeded_cells(rows)
    n_seeds = sorted({len({r.get("seed") for r in rows if r["variation"] == c}) for c in seeded})
    text = "each rendered once" if n_starts == 1 else f"each rendered {n_starts} times"
    if seeded:
        text += (f" ({', '.join(seeded)}: {' or '.join(str(n * n_starts) for n in n_seeds)} "
                 f"times, once per seed{' and start' if n_starts > 1 else ''})")
    text += " and replayed through both flows"
    if n_starts > 1 or seeded:
        text += "; a cell's value is the median over its runs"
    return text


def _seeded_cells(rows: list[dict[str, Any]]) -> list[str]:
    """The cells that ran with several seeds (rows with a ``seed``), in row order."""
    seeds: dict[str, set] = {}
    for r in rows:
        if r.get("seed") is not None:
            seeds.setdefault(r["variation"], set()).add(r["seed"])
    return [c for c, s in seeds.items() if len(s) > 1]


def _comparison_only(m: Manifest) -> set[str]:
    """Sweeps shown in the comparison section only (not the evaluation sweep)."""
    if not m.comparison:
        return set()
    return {c["sweep"] for c in m.comparison["chains"]} - {m.evaluation.get("sweep")}


def _comparison_section(m: Manifest, src: _Sources) -> list[str]:
    """One table: each chain of the manifest's ``comparison`` on every evaluation cell, the
    median over the cells every chain ran beside it; then the full tables of the sweeps shown
    only here."""
    cfg = m.comparison
    if not cfg:
        return []
    chains, keys = cfg["chains"], list(cfg.get("metrics") or [])
    ref = m.evaluation.get("reference_cell")
    out = [f"## {cfg.get('title', 'Comparison')}", ""]
    if cfg.get("description"):
        out += [str(cfg["description"]).strip(), ""]
    docs = {c["sweep"]: src.sweeps.get(c["sweep"]) for c in chains}
    missing = [name for name, doc in docs.items() if not doc]
    if missing:
        out += ["Not measured yet: " + ", ".join(f"`evchain results --run {n}`"
                                                 for n in missing) + ".", ""]
    cells: list[str] = []
    for doc in docs.values():
        for r in (doc or {}).get("rows", []):
            if r["variation"] not in cells:
                cells.append(r["variation"])
    if ref in cells:
        cells = [ref] + [c for c in cells if c != ref]

    def rows_of(c):
        doc = docs[c["sweep"]]
        return doc["rows"] if doc else []

    ran = {c["label"]: {r["variation"] for r in rows_of(c) if r.get("base") == c["base"]}
           for c in chains}
    common = [c for c in cells if c != ref and all(c in v for v in ran.values())]
    for doc in docs.values():
        if doc:
            out.append(f"`{doc['file']}`: {doc['wall_s']:g} s wall on "
                       f"{_machine_text(doc.get('machine'))}; reproduce: `{doc['command']}`.")
    out += ["", f"Median over the {len(common)} evaluation cells every chain ran:", ""]
    head = ["chain"] + [_metric_meta(m, k)["label"] for k in keys]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in chains:
        vals = []
        for k in keys:
            per = [collect(rows_of(c), {"variation": cell, "base": c["base"]}, k).median
                   for cell in common]
            per = [v for v in per if v is not None]
            vals.append(_fmt(statistics.median(per) if per else None,
                             _metric_meta(m, k)["format"]))
        out.append("| " + " | ".join([_cell(c["label"]), *vals]) + " |")
    out += ["", "Every cell (- where a chain's sweep has no such cell or the metric is not "
            "defined there):", ""]
    head = ["cell", "chain"] + [_metric_meta(m, k)["label"] for k in keys]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cell in cells:
        for c in chains:
            vals = [_value_text(collect(rows_of(c), {"variation": cell, "base": c["base"]}, k),
                                _metric_meta(m, k)["format"]) for k in keys]
            out.append("| " + " | ".join([cell, _cell(c["label"]), *vals]) + " |")
    out.append("")
    for name in sorted(_comparison_only(m)):
        doc = src.sweeps.get(name)
        if doc:
            out += [f"### {m.titles[name]}", "", doc.get("description", ""), ""]
            out += _sweep_table(m, doc["rows"], doc["report"]) + [""]
    return out


def _bench_section(m: Manifest, src: _Sources) -> list[str]:
    if not m.bench:
        return []
    out = ["## Benchmarks", "",
           "Throughput next to the error each row reached; `limit` is the ratio to a physical "
           "limit measured in the same run (time of a plain numpy pass over the same bytes / "
           "time of the stage) where the row has one.", ""]
    for entry in m.bench:
        doc = src.bench.get(entry["prefix"])
        out.append(f"### {entry['prefix']}")
        out.append("")
        if not doc:
            out += [f"Not measured yet: `evchain results --run {entry['prefix']}`.", ""]
            continue
        out += [f"{doc['repeat']} repeats{', --quick' if doc.get('quick') else ''}; "
                f"{doc['wall_s']:g} s wall on {_machine_text(doc.get('machine'))}. "
                f"Reproduce: `{doc['command']}`.", "",
                "| row | stage | data | throughput | unit | error | error name | limit |",
                "|---|---|---|---|---|---|---|---|"]
        rows = doc["rows"]
        for wl in dict.fromkeys(r["workload"] for r in rows):
            mine = [r for r in rows if r["workload"] == wl]
            first = mine[0]
            data = first.get("data") or first.get("scene") or "-"
            if first.get("params_from"):
                data += f"; parameters from `{first['params_from']}`"
            out.append(
                f"| {_cell(wl)} | {_cell(first.get('stage'))} | {_cell(data)} | "
                f"{_value_text(collect(mine, {}, 'throughput'), '.3g')} | {first.get('unit')} | "
                f"{_value_text(collect(mine, {}, 'error'), '.3g')} | "
                f"{_cell(first.get('error_name') or '-')} | "
                f"{_value_text(collect(mine, {}, 'limit_ratio'), '.2f')} |")
        out.append("")
    return out


# -- the command ---------------------------------------------------------------------------------

def write(m: Manifest) -> Path:
    target = m.root / OUTPUT
    atomic_write_text(target, render(m))
    return target


def check(m: Manifest) -> tuple[bool, str]:
    """Whether docs/results.md is what the saved results give, and a message saying so."""
    target = m.root / OUTPUT
    want = render(m)
    have = target.read_text(encoding="utf-8") if target.is_file() else None
    if have == want:
        return True, f"{target} is current"
    if have is None:
        return False, f"{target} is missing: run evchain results"
    import difflib

    diff = list(difflib.unified_diff(have.splitlines(), want.splitlines(), str(target),
                                     "from results/", lineterm="", n=0))
    shown = "\n".join(diff[:20]) + ("\n..." if len(diff) > 20 else "")
    return False, f"{target} differs from what results/ gives: run evchain results\n{shown}"

