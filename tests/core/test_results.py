"""``evchain results``: verdicts from repeats, docs/results.md from saved JSON, --check."""

import json

import pytest

from evchain import ConfigError
from evchain.cli import main
from evchain.results import Value, load_manifest, render, verdict

MANIFEST = """sweeps:
  ref: ref.yaml
  ev: ev.yaml
evaluation: {sweep: ev, reference_cell: reference}
bench:
  - {prefix: toy-, repeat: 3}
metrics:
  foe.dx_mean_px: {label: "FOE |dx| px", better: lower, format: ".2f"}
  ttc.share: {label: "TTC share", better: higher, format: ".1%"}
goals:
  - {name: dx lk, source: "sweep:ref", select: {base: lk}, metric: foe.dx_mean_px,
     goal: "<= 2"}
  - {name: share lk, source: "sweep:ref", select: {base: lk}, metric: ttc.share, goal: ">= 0.8"}
  - {name: toy speed, source: bench, select: {workload: toy-a}, metric: throughput,
     goal: ">= 100"}
"""


def sweep_doc(rows, report=("foe.dx_mean_px", "ttc.share")):
    return {"sweep": "x", "file": "pipelines/sweeps/x.yaml", "description": "A sweep.",
            "report": list(report), "wall_s": 12.0, "command": "evchain results --run x",
            "machine": {"cores": 2, "cpu": "Test CPU", "load": 0.5, "evchain": "0.1.0",
                        "commit": "abc"}, "rows": rows}


@pytest.fixture
def root(tmp_path):
    (tmp_path / "results" / "sweeps").mkdir(parents=True)
    (tmp_path / "results" / "bench").mkdir()
    (tmp_path / "docs").mkdir()
    (tmp_path / "results" / "results.yaml").write_text(MANIFEST)
    ref = [{"variation": "whole", "base": b, "repeat": r, "foe.dx_mean_px": dx,
            "ttc.share": sh}
           for b, dxs, shs in (("lk", (1.9, 1.95, 1.98), (0.9, 0.91, 0.95)),
                               ("plane", (2.5, 2.6, 2.7), (0.5, 0.6, 0.7)))
           for r, (dx, sh) in enumerate(zip(dxs, shs, strict=True))]
    ev = [{"variation": c, "base": b, "foe.dx_mean_px": dx, "ttc.share": sh}
          for c, dx, sh in (("reference", 2.0, 0.9), ("a", 3.0, 0.5), ("b", 5.0, None),
                            ("c", 4.0, 0.7))
          for b in ("lk", "plane")]
    (tmp_path / "results" / "sweeps" / "ref.json").write_text(json.dumps(sweep_doc(ref)))
    (tmp_path / "results" / "sweeps" / "ev.json").write_text(json.dumps(sweep_doc(ev)))
    bench = {"prefix": "toy-", "quick": False, "repeat": 3, "command": "evchain results --run toy-",
             "machine": {"cores": 2, "cpu": "Test CPU", "load": 1.0}, "wall_s": 3.0,
             "rows": [{"workload": "toy-a", "stage": "toy", "throughput": t, "unit": "ev/s",
                       "error": 0.1, "error_name": "median |dt| us", "limit_ratio": None,
                       "data": "synthetic toy", "repeat": r}
                      for r, t in enumerate((150.0, 160.0, 155.0))]}
    (tmp_path / "results" / "bench" / "toy-.json").write_text(json.dumps(bench))
    return tmp_path


@pytest.mark.parametrize("values, op, target, word", [
    ([1.0, 1.1, 1.2], "<=", 2.0, "met"),           # margin 0.9 > spread 0.2
    ([1.8, 1.9, 2.1], "<=", 2.0, "borderline"),    # margin 0.1 inside spread 0.3
    ([2.0, 2.1, 2.1], ">=", 2.2, "not met"),       # no repeat meets it
    ([1.9, 2.0, 2.9], "<=", 2.0, "borderline"),    # some repeats meet it, some do not
    ([1.0, 1.5, 1.9], "<=", 2.0, "borderline"),    # all meet it, margin 0.5 < spread 0.9
    ([3.0, 3.1, 3.2], "<=", 2.0, "not met"),
    ([0.9, 0.9, 0.9], ">=", 0.8, "met"),           # deterministic: spread 0
    ([0.79, 0.79, 0.79], ">=", 0.8, "not met"),
    ([1.0], "<=", 2.0, "unrepeated"),
    ([], "<=", 2.0, "no data"),
])
def test_verdicts(values, op, target, word):
    assert verdict(Value(values), op, target)[1] == word


def test_page_from_saved_results(root):
    text = render(load_manifest(root))
    assert ("| dx lk | sweep ref (base lk) | 1.95 (1.90-1.98, x3) | <= 2.00 | 0.05 | "
            "borderline |") in text
    assert "| share lk | sweep ref (base lk) | 91.0% (90.0%-95.0%, x3) | >= 80.0% | 11.0% | met |" \
        in text
    assert "| toy speed | toy-a: synthetic toy | 155 (150-160, x3) | >= 100 | 55 | met |" in text
    assert "| 0.1 (x3, equal) | median \\|dt\\| us | - |" in text          # pipes escaped
    # evaluation summary: median and worst over the cells a, b, c; the reference beside them
    assert "| FOE |dx| px |" not in text                               # pipes escaped
    assert "| FOE \\|dx\\| px | 2.00 | 4.00 | 5.00 (b) | 2.00 | 4.00 | 5.00 (b) |" in text
    assert "| TTC share | 90.0% | 60.0% | 50.0% (a) |" in text        # b has no TTC
    assert "3 cells" in text and "Test CPU" in text
    assert "## ref" in text and "| whole | lk | 1.95 (1.90-1.98, x3) |" in text
    assert render(load_manifest(root)) == text                          # deterministic


def test_check_and_write(root, monkeypatch, capsys):
    monkeypatch.chdir(root)
    assert main(["results", "--check"]) == 1
    assert "missing" in capsys.readouterr().err
    assert main(["results"]) == 0
    assert main(["results", "--check"]) == 0
    doc = json.loads((root / "results" / "sweeps" / "ref.json").read_text())
    doc["rows"][0]["foe.dx_mean_px"] = 2.5
    (root / "results" / "sweeps" / "ref.json").write_text(json.dumps(doc))
    assert main(["results", "--check"]) == 1
    assert "differs" in capsys.readouterr().err


@pytest.mark.parametrize("bad, pattern", [
    (MANIFEST.replace('goal: "<= 2"', 'goal: "< 2"'), "must read"),
    (MANIFEST.replace('source: "sweep:ref", select: {base: lk}, metric: ttc.share',
                      'source: "sweep:nope", select: {base: lk}, metric: ttc.share'),
     "sweep:nope"),
    (MANIFEST + "extra: 1\n", "extra: unknown key"),
])
def test_manifest_errors(root, bad, pattern):
    (root / "results" / "results.yaml").write_text(bad)
    with pytest.raises(ConfigError, match=pattern):
        load_manifest(root)


def test_unknown_name_to_run(root):
    with pytest.raises(ConfigError, match="nope: not in the manifest"):
        from evchain.results import run_and_save

        run_and_save(load_manifest(root), ["nope"])


def test_comparison_table(root):
    (root / "results" / "results.yaml").write_text(
        MANIFEST.replace("  ev: ev.yaml\n", "  ev: ev.yaml\n  fr: fr.yaml\n") +
        "comparison:\n  title: Events and frames\n  metrics: [foe.dx_mean_px, ttc.share]\n"
        "  chains:\n    - {label: events lk, sweep: ev, base: lk}\n"
        "    - {label: frames 30, sweep: fr, base: f30}\n")
    before = render(load_manifest(root))
    assert "## Events and frames" in before and "`evchain results --run fr`" in before
    fr = [{"variation": c, "base": "f30", "foe.dx_mean_px": dx, "ttc.share": 0.4}
          for c, dx in (("reference", 0.5), ("a", 1.0), ("c", 3.0))]
    (root / "results" / "sweeps" / "fr.json").write_text(json.dumps(sweep_doc(fr)))
    text = render(load_manifest(root))
    # the median over the cells both chains ran (a and c; b has no frames run)
    assert "Median over the 2 evaluation cells every chain ran" in text
    assert "| events lk | 3.50 | 60.0% |" in text and "| frames 30 | 2.00 | 40.0% |" in text
    assert "| b | frames 30 | - | - |" in text and "| reference | frames 30 | 0.50 | 40.0% |" \
        in text
    # the existing sections are unchanged, the frames sweep is shown in the comparison only
    assert text.startswith(before.split("## Events and frames")[0])
    assert "\n## fr\n" not in text and "\n### fr\n" in text


def test_cells_over_seeds_show_the_median_and_range(root):
    path = root / "results" / "sweeps" / "ev.json"
    doc = json.loads(path.read_text())
    rows = [{**r, "repeat": 0, "seed": None} for r in doc["rows"]]
    # cell d over three seeds: 2, 6 and 3 (median 3); its TTC share only on two seeds
    rows += [{"variation": "d", "base": b, "repeat": k, "seed": seed, "foe.dx_mean_px": dx,
              "ttc.share": sh}
             for b in ("lk", "plane")
             for k, (seed, dx, sh) in enumerate(((0, 2.0, 0.2), (1, 6.0, None), (2, 3.0, 0.4)))]
    doc["rows"] = rows
    path.write_text(json.dumps(doc))
    text = render(load_manifest(root))
    assert "| d | lk | 3.00 (2.00-6.00, x3) | 30.0% (20.0%-40.0%, x2) |" in text
    assert "| a | lk | 3.00 | 50.0% |" in text                        # one run: no range
    # the summary takes d's median (3.00) as one cell: median of a 3, b 5, c 4, d 3 = 3.5;
    # the worst share is d's median 30 %
    assert "| FOE \\|dx\\| px | 2.00 | 3.50 | 5.00 (b) |" in text
    assert "| TTC share | 90.0% | 50.0% | 30.0% (d) |" in text
    assert "4 cells, each rendered once (d: 3 times, once per seed) and replayed through both " \
           "flows; a cell's value is the median over its runs" in text


def test_cells_over_starts_and_seeds_say_how_often_they_ran(root):
    """A sweep that repeats every cell (three starts) says so (three runs per plain cell, nine
    for a cell over three seeds as well), and the summary gives each value's range over the
    starts: each start's cells alone (a seeded cell by its median over the seeds there)."""
    path = root / "results" / "sweeps" / "ev.json"
    doc = json.loads(path.read_text())
    # start k adds k to every |dx|: a 3, b 5, c 4 -> 3 + k, 5 + k, 4 + k
    rows = [{**r, "repeat": k, "seed": None, "foe.dx_mean_px": r["foe.dx_mean_px"] + k}
            for r in doc["rows"] for k in range(3)]
    # d: seeds 1, 2, 9 at start 0 (median 2), 2, 3, 9 at start 1 (3), 8, 9, 9 at start 2 (9)
    dx_d = [1.0, 2.0, 9.0, 2.0, 3.0, 9.0, 8.0, 9.0, 9.0]
    rows += [{"variation": "d", "base": b, "repeat": k, "seed": k % 3,
              "foe.dx_mean_px": dx_d[k], "ttc.share": 0.2}
             for b in ("lk", "plane") for k in range(9)]
    doc["rows"] = rows
    path.write_text(json.dumps(doc))
    text = render(load_manifest(root))
    assert "4 cells, each rendered 3 times (d: 9 times, once per seed and start) and " \
           "replayed through both flows; a cell's value is the median over its runs" in text
    # all runs (reference 2 + k: 3): a 4, b 6, c 5, d 8 -> median 5.5, worst d 8; start 0:
    # a 3, b 5, c 4, d 2 -> 3.5, worst b 5; start 1: 4, 6, 5, 3 -> 4.5, b 6; start 2: 5, 7, 6,
    # 9 -> 6.5, d 9
    assert "| FOE \\|dx\\| px | 3.00 | 5.50 (3.50-6.50) | 8.00 (d; 5.00-9.00) |" in text


def test_a_workload_belongs_to_the_longest_prefix(root, monkeypatch):
    """``toy-`` leaves ``toy-peer-*`` to the entry ``toy-peer``; an entry whose workloads give
    no rows (peers not installed) saves an empty table, not an error."""
    from evchain import results
    from evchain.bench import BenchRow
    from evchain.core import registry

    (root / "results" / "results.yaml").write_text(
        MANIFEST.replace("  - {prefix: toy-, repeat: 3}\n",
                         "  - {prefix: toy-, repeat: 1}\n  - {prefix: toy-peer, repeat: 1}\n"))
    ran = []

    def workload(name, rows):
        def run(quick):
            ran.append(name)
            return [BenchRow(name, "toy", 1.0, "ev/s", data="synthetic toy")] if rows else []
        return run

    fake = type("Registry", (), {"workloads": {"toy-a": workload("toy-a", True),
                                               "toy-peer-a": workload("toy-peer-a", False)}})
    monkeypatch.setattr(registry, "make_registry", lambda: fake)
    m = load_manifest(root)
    saved = results.run_and_save(m, ["toy-", "toy-peer"], echo=lambda s: None)
    assert [p.name for p in saved] == ["toy-.json", "toy-peer.json"]
    assert ran == ["toy-a", "toy-peer-a"]                      # each once, by its own entry
    toy = json.loads(saved[0].read_text())
    peer = json.loads(saved[1].read_text())
    assert [r["workload"] for r in toy["rows"]] == ["toy-a"] and peer["rows"] == []
    text = render(load_manifest(root))
    assert "### toy-peer\n\n1 repeats;" in text and "| toy-a | toy |" in text
