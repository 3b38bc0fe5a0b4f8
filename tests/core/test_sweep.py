import json
from pathlib import Path

import pytest
import yaml

from evchain import ConfigError
from evchain.sweep import load_sweep, run_sweep

BASE = "chain:\n  - use: toy_source\n  - use: toy_writer\n"


def write(tmp_path, sweep_text):
    (tmp_path / "base.yaml").write_text(BASE)
    p = tmp_path / "s.yaml"
    p.write_text(sweep_text)
    return p


def test_one_at_a_time_and_cache(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nset: [toy_source.packets=2]\nvary:\n"
                        "  toy_source.events_per_packet: [5, 7]\n  toy_source.width: [40]\n"
                        "report: [toy.count, toy.missing]\n")
    sweep = load_sweep(p)
    assert [v.label for v in sweep.variations] == [
        "toy_source.events_per_packet=5", "toy_source.events_per_packet=7", "toy_source.width=40"]
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert [r["toy.count"] for r in rows] == [10, 14, 200]
    assert all(r["toy.missing"] is None and not r["cached"] for r in rows)
    again = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert all(r["cached"] for r in again)
    assert (tmp_path / "out" / "sweep.md").read_text().startswith("| variation |")


def test_set_from_the_command_line_joins_the_sweeps_set(tmp_path, registry):
    """``--set`` comes after the file's ``set`` (it wins over it) and before each variation's
    own overrides (they still win); the table's JSON says which were given."""
    p = write(tmp_path, "base: base.yaml\nset: [toy_source.packets=2]\nvary:\n"
                        "  toy_source.events_per_packet: [5, 7]\n  toy_source.packets: [1]\n"
                        "report: [toy.count]\n")
    sweep = load_sweep(p, ["toy_source.packets=3", "toy_source.width=40"])
    assert sweep.variations[0].overrides == [
        "toy_source.packets=2", "toy_source.packets=3", "toy_source.width=40",
        "toy_source.events_per_packet=5"]
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert [r["toy.count"] for r in rows] == [15, 21, 100]  # 3 x 5, 3 x 7, the cell's 1 x 100
    assert json.loads((tmp_path / "out" / "sweep.json").read_text())["extra_set"] == [
        "toy_source.packets=3", "toy_source.width=40"]
    with pytest.raises(ConfigError, match=r"s.yaml: --set 'toy_source.packets': expected "
                                          r"STAGE.PARAM=VALUE"):
        load_sweep(p, ["toy_source.packets"])


def test_grid(tmp_path):
    p = write(tmp_path, "base: base.yaml\nmode: grid\nvary:\n  a.x: [1, 2]\n  b.y: [3, 4, 5]\n")
    assert len(load_sweep(p).variations) == 6


@pytest.mark.parametrize("text, pattern", [
    ("base: base.yaml\n", "needs 'base'"),
    ("base: base.yaml\nvary: {a.b: []}\n", r"s.yaml:2:7: vary: must map"),
    ("base: base.yaml\nvary: {a.b: [1]}\nmode: all\n", "mode: must be"),
    ("base: base.yaml\nvary: {a.b: [1]}\nvarry: 1\n", "varry: unknown key"),
])
def test_sweep_errors(tmp_path, text, pattern):
    with pytest.raises(ConfigError, match=pattern):
        load_sweep(write(tmp_path, text))


def test_bad_variation_fails_before_running(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nvary:\n  toy_source.packets: [1, -3]\n")
    with pytest.raises(ConfigError, match="toy_source.packets"):
        run_sweep(load_sweep(p), tmp_path / "out", workers=1, registry=registry)
    assert not (tmp_path / "out").exists()


def test_joint_keys(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nvary:\n  toy_source.packets,toy_source.width: "
                        "[[1, 20], [2, 30]]\nreport: [toy.count]\n")
    sweep = load_sweep(p)
    assert sweep.variations[1].overrides == ["toy_source.packets=2", "toy_source.width=30"]
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert [r["toy.count"] for r in rows] == [100, 200]
    import csv  # the joint key's label holds commas: the CSV must still read back

    table = list(csv.DictReader((tmp_path / "out" / "sweep.csv").open()))
    assert [r["variation"] for r in table] == [v.label for v in sweep.variations]
    assert [int(r["toy.count"]) for r in table] == [100, 200]
    bad = write(tmp_path, "base: base.yaml\nvary:\n  a.b,c.d: [[1]]\n")
    with pytest.raises(ConfigError, match="list of 2 values"):
        load_sweep(bad)


def test_cells_bases_and_repeats(tmp_path, registry):
    (tmp_path / "other.yaml").write_text(BASE)
    p = write(tmp_path, "bases: {a: base.yaml, b: other.yaml}\nreport: [toy.count]\n"
                        "repeat: [[], [toy_source.events_per_packet=3]]\n"
                        "cells:\n  small: [toy_source.packets=1]\n  big: [toy_source.packets=4]\n")
    sweep = load_sweep(p)
    assert [v.label for v in sweep.variations] == ["small", "big"]
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    got = [(r["variation"], r["repeat"], r["base"], r["toy.count"]) for r in rows]
    assert got == [("small", 0, "a", 100), ("small", 0, "b", 100), ("small", 1, "a", 3),
                   ("small", 1, "b", 3), ("big", 0, "a", 400), ("big", 0, "b", 400),
                   ("big", 1, "a", 12), ("big", 1, "b", 12)]
    summary = json.loads((tmp_path / "out" / "sweep.json").read_text())
    assert summary["rows"] == rows and summary["machine"]["cores"] >= 1


def test_cells_repeated_over_seeds(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nreport: [toy.count]\n"
                        "repeat: [[], [toy_source.events_per_packet=3]]\n"
                        "cells:\n  plain: [toy_source.packets=1]\n"
                        "  seeded: {set: [toy_source.packets=2], seeds: [0, 3]}\n")
    sweep = load_sweep(p)
    seeded = sweep.variations[1]
    assert seeded.seeds == [0, 3] and sweep.repeat_count(seeded) == 4
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    got = [(r["variation"], r["repeat"], r["seed"], r["toy.count"]) for r in rows]
    # every sweep repeat times every seed, the seed after the cell's and the repeat's overrides
    assert got == [("plain", 0, None, 100), ("plain", 1, None, 3),
                   ("seeded", 0, 0, 200), ("seeded", 1, 3, 200), ("seeded", 2, 0, 6),
                   ("seeded", 3, 3, 6)]
    seeds = [json.loads((tmp_path / "out" / r["run"] / "report.json").read_text())["seed"]
             for r in rows]
    assert seeds == [0, 0, 0, 3, 0, 3]                  # the base's seed is 0
    assert len({r["run"] for r in rows}) == 6           # each seed its own run
    assert sweep.overrides(seeded, 3) == ["toy_source.packets=2",
                                          "toy_source.events_per_packet=3", "seed=3"]


def test_seeds_render_once_per_seed_with_record(tmp_path):
    (tmp_path / "record.yaml").write_text(RECORD)
    (tmp_path / "lk.yaml").write_text(REPLAYED.format(flow="lk_flow"))
    p = tmp_path / "s.yaml"
    p.write_text("base: lk.yaml\nrecord: record.yaml\nreport: [flow.n_scored]\ncells:\n"
                 "  mm: {set: [emulator.mismatch_sigma=0.05], seeds: [1, 2]}\n")
    rows = run_sweep(load_sweep(p), tmp_path / "out", workers=1, echo=lambda s: None)
    records = sorted((tmp_path / "out").glob("record-*"))
    assert len(records) == 2                             # one recording per seed
    assert sorted(yaml.safe_load((r / "pipeline.resolved.yaml").read_text())["seed"]
                  for r in records) == [1, 2]
    assert [(r["repeat"], r["seed"]) for r in rows] == [(0, 1), (1, 2)]
    events = [(r / "events.aedat").read_bytes() for r in records]
    assert events[0] != events[1]                        # the mismatch follows the seed


@pytest.mark.parametrize("cell, pattern", [
    ("{set: [a.b=1], seeds: []}", "seeds must be a non-empty list"),
    ("{set: [a.b=1], seeds: [1, 1]}", "distinct"),
    ("{set: [a.b=1], seeds: [-1]}", "integers >= 0"),
    ("{set: [a.b=1], seeds: [1.5]}", "integers >= 0"),
    ("{set: [a.b=1], seeds: 3}", "non-empty list"),
    ("{set: [seed=4], seeds: [1]}", "sets seed= and seeds"),
    ("{sets: [a.b=1]}", "cell 'x' must be a list"),
    ("{set: a.b=1}", "cell 'x' must be a list"),
])
def test_seeded_cell_errors(tmp_path, cell, pattern):
    with pytest.raises(ConfigError, match=pattern):
        load_sweep(write(tmp_path, f"base: base.yaml\ncells:\n  x: {cell}\n"))


@pytest.mark.parametrize("text, pattern", [
    ("base: base.yaml\nbases: {a: base.yaml}\nvary: {a.b: [1]}\n", "needs 'base'"),
    ("bases: [base.yaml]\nvary: {a.b: [1]}\n", "bases: must map"),
    ("base: base.yaml\ncells: {x: [a.b=1]}\nvary: {c.d: [2]}\nrepeat: []\n", "repeat: must"),
    ("base: base.yaml\ncells: {x: a.b=1}\n", "cells: cell 'x' must be a list"),
    ("base: base.yaml\nrecord: r.yaml\nreplay: e.aedat\ncells: {x: []}\n", "not both"),
])
def test_sweep_errors_new_keys(tmp_path, text, pattern):
    with pytest.raises(ConfigError, match=pattern):
        load_sweep(write(tmp_path, text))


SCENE_EMULATOR = """chain:
  - use: scene
    scenario: high-rise
    width: 32
    height: 24
    supersample: 1
    start_m: 200
    duration_s: 0.05
    max_motion_px: 1.0
  - use: emulator
    threshold_on: 0.3
    threshold_off: 0.3
"""
RECORD = SCENE_EMULATOR + "  - use: aedat_writer\n    path: events.aedat\n"
REPLAYED = SCENE_EMULATOR + "  - use: {flow}\n  - use: flow_scorer\n"


def test_record_renders_each_variation_once_and_every_base_replays_it(tmp_path):
    (tmp_path / "record.yaml").write_text(RECORD)
    (tmp_path / "lk.yaml").write_text(REPLAYED.format(flow="lk_flow"))
    (tmp_path / "plane.yaml").write_text(REPLAYED.format(flow="plane_flow"))
    p = tmp_path / "s.yaml"
    p.write_text("bases: {lk: lk.yaml, plane: plane.yaml}\nrecord: record.yaml\n"
                 "report: [flow.n_scored]\ncells:\n  ref: []\n"
                 "  thr: [emulator.threshold_on=0.5, emulator.threshold_off=0.5, "
                 "lk_flow.search_distance=3]\n")
    sweep = load_sweep(p)
    out = tmp_path / "out"
    rows = run_sweep(sweep, out, workers=1, echo=lambda s: None)
    records = sorted(out.glob("record-*"))
    assert len(records) == 2                             # one recording per cell, not per base
    for rec in records:
        assert (rec / "events.aedat").stat().st_size > 0
        chain = yaml.safe_load((rec / "pipeline.resolved.yaml").read_text())["chain"]
        assert [s["use"] for s in chain] == ["scene", "emulator", "aedat_writer"]
    assert [(r["variation"], r["base"]) for r in rows] == [
        ("ref", "lk"), ("ref", "plane"), ("thr", "lk"), ("thr", "plane")]
    for r in rows:
        rep = json.loads((out / r["run"] / "report.json").read_text())
        first = rep["pipeline"]["chain"][0]
        assert first["use"] == "scene_events"             # replayed, not rendered again
        assert Path(first["path"]).parent.name.startswith("record-")
    thr = json.loads((out / rows[2]["run"] / "report.json").read_text())["pipeline"]["chain"]
    assert [s.get("search_distance") for s in thr if s["use"] == "lk_flow"] == [3]
    again = run_sweep(sweep, out, workers=1, echo=lambda s: None)
    assert all(r["cached"] for r in again)


def test_a_change_outside_a_runs_code_keeps_it_cached(tmp_path, monkeypatch):
    """The source hash of a run covers the code it can execute: a change that only the LK
    chain's code sees (an lk_flow file, say) repeats the LK replays, not the recordings (scene,
    emulator, writer) nor the plane replays."""
    import evchain.provenance as provenance

    (tmp_path / "record.yaml").write_text(RECORD)
    (tmp_path / "lk.yaml").write_text(REPLAYED.format(flow="lk_flow"))
    (tmp_path / "plane.yaml").write_text(REPLAYED.format(flow="plane_flow"))
    p = tmp_path / "s.yaml"
    p.write_text("bases: {lk: lk.yaml, plane: plane.yaml}\nrecord: record.yaml\n"
                 "report: [flow.n_scored]\ncells:\n  ref: []\n")
    out = tmp_path / "out"
    run_sweep(load_sweep(p), out, workers=1, echo=lambda s: None)
    recording = next(out.glob("record-*")) / "report.json"
    written = recording.stat().st_mtime_ns
    stamp = provenance.run_source_stamp

    def lk_edited(spec):
        edited = any(s.use == "lk_flow" for s in spec.stages)
        return stamp(spec) + ("-edited" if edited else "")

    monkeypatch.setattr(provenance, "run_source_stamp", lk_edited)
    lines = []
    again = run_sweep(load_sweep(p), out, workers=1, echo=lines.append)
    assert [(r["base"], r["cached"]) for r in again] == [("lk", False), ("plane", True)]
    assert recording.stat().st_mtime_ns == written       # not recorded again
    assert sum("run again: the code changed" in line for line in lines) == 1


def test_record_pipeline_must_write_events(tmp_path):
    (tmp_path / "record.yaml").write_text(RECORD.replace("  - use: aedat_writer\n"
                                                         "    path: events.aedat\n", ""))
    (tmp_path / "lk.yaml").write_text(REPLAYED.format(flow="lk_flow"))
    p = tmp_path / "s.yaml"
    p.write_text("base: lk.yaml\nrecord: record.yaml\ncells: {ref: []}\n")
    with pytest.raises(ConfigError, match="aedat_writer"):
        run_sweep(load_sweep(p), tmp_path / "out", workers=1, echo=lambda s: None)


def test_override_of_no_stage_is_an_error(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\ncells: {x: [toy_sorce.packets=1]}\n")
    with pytest.raises(ConfigError, match="toy_sorce.packets=1.*addresses no stage"):
        run_sweep(load_sweep(p), tmp_path / "out", workers=1, registry=registry)


# -- cache keys, paths, failures, progress ----------------------------------------------------

FILE_BASE = ("chain:\n  - use: aedat\n    path: ../data/ev.aedat\n  - use: refractory\n"
             "  - use: aedat_writer\n    path: kept.aedat\n")


def file_sweep(tmp_path, n_events=400):
    """A sweep in sweeps/ over a pipeline in pipes/ reading data/ev.aedat (all relative)."""
    from evchain.io.aedat2 import write_aedat2
    from evchain.testing.synthetic import random_events

    for d in ("data", "pipes", "sweeps"):
        (tmp_path / d).mkdir(exist_ok=True)
    write_aedat2(tmp_path / "data" / "ev.aedat", random_events(n_events, seed=n_events),
                 chip="davis240")
    (tmp_path / "pipes" / "p.yaml").write_text(FILE_BASE)
    p = tmp_path / "sweeps" / "s.yaml"
    p.write_text("base: ../pipes/p.yaml\nvary:\n  refractory.period_us: [100, 1000000]\n"
                 "report: [aedat_writer.events]\n")
    return p


def test_changed_input_file_is_not_answered_from_the_cache(tmp_path, monkeypatch):
    p = file_sweep(tmp_path)
    monkeypatch.chdir(tmp_path / "data")  # paths are relative to the files, not to here
    rows = run_sweep(load_sweep(p), tmp_path / "out", workers=1, echo=lambda s: None)
    assert not any(r["cached"] for r in rows) and rows[0]["aedat_writer.events"] > 0
    again = run_sweep(load_sweep(p), tmp_path / "out", workers=1, echo=lambda s: None)
    assert all(r["cached"] for r in again)
    file_sweep(tmp_path, n_events=900)  # same file name, other events
    lines = []
    changed = run_sweep(load_sweep(p), tmp_path / "out", workers=1, echo=lines.append)
    assert not any(r["cached"] for r in changed)
    assert all("(run again: an input file changed)" in line for line in lines)
    assert changed[0]["aedat_writer.events"] > rows[0]["aedat_writer.events"]
    rep = json.loads((tmp_path / "out" / changed[0]["run"] / "report.json").read_text())
    assert rep["inputs"]["aedat.path"]["path"] == str(tmp_path / "data" / "ev.aedat")


def test_changed_code_is_not_answered_from_the_cache(tmp_path, monkeypatch):
    """A changed kernel (any source file of evchain or a plugin) means another source hash in
    the report's versions: the run is repeated."""
    import evchain.core.chain as chain

    p = file_sweep(tmp_path)
    run_sweep(load_sweep(p), tmp_path / "out", workers=1, echo=lambda s: None)
    stamps = chain.source_stamps

    def edited(registry, spec=None):
        out = stamps(registry, spec)
        return {**out, "evchain": out["evchain"] + "-edited"}

    monkeypatch.setattr(chain, "source_stamps", edited)
    lines = []
    again = run_sweep(load_sweep(p), tmp_path / "out", workers=1, echo=lines.append)
    assert not any(r["cached"] for r in again)
    assert all("(run again: the code changed)" in line for line in lines)


def test_source_stamps_follow_the_files(tmp_path, monkeypatch):
    import evchain
    from evchain.core.registry import make_registry
    from evchain.provenance import source_stamps, tree_stamp

    whole = tree_stamp(Path(evchain.__file__).parent)
    assert source_stamps(make_registry(discover=False))["evchain"] == whole
    pkg = tmp_path / "some_plugin"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "kernel.py").write_text("def f(x):\n    return x + 1\n")
    before = tree_stamp(pkg)
    (pkg / "kernel.py").write_text("def f(x):\n    return x + 2\n")
    assert tree_stamp(pkg) != before


def test_failed_runs_are_marked_and_named(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nvary:\n  toy_source.fail_at_packet: [null, 1, 5]\n"
                        "report: [toy.count]\n")
    from evchain.sweep import SweepFailed

    lines = []
    with pytest.raises(SweepFailed, match=r"1 of 3 runs failed: toy_source.fail_at_packet=1 "
                                          r"\[\w+\]; the table .*sweep.md\) marks them"):
        run_sweep(load_sweep(p), tmp_path / "out", workers=1, registry=registry,
                  echo=lines.append)
    rows = json.loads((tmp_path / "out" / "sweep.json").read_text())["rows"]
    assert [r["status"] for r in rows] == [
        "ok", "failed: filter 'toy_source' (toy_source) failed in packets: ValueError: boom",
        "ok"]
    assert [r["toy.count"] for r in rows] == [300, None, 300]
    assert "| failed: filter 'toy_source'" in (tmp_path / "out" / "sweep.md").read_text()
    assert [s.split("]")[0] for s in lines] == ["  [1/3", "  [2/3", "  [3/3"]
    assert "FAILED: filter 'toy_source'" in lines[1]


def test_a_line_per_run_as_it_finishes(tmp_path, registry):
    """Each run's line is printed when it finishes, before the next run starts."""
    p = write(tmp_path, "base: base.yaml\nvary:\n  toy_source.packets: [1, 2, 3]\n"
                        "report: [toy.count]\n")
    seen = []
    out = tmp_path / "out"

    def echo(line):  # what is on disk when the line comes
        seen.append((line, sorted(d.name for d in out.iterdir() if d.is_dir())))

    rows = run_sweep(load_sweep(p), out, workers=1, registry=registry, echo=echo)
    assert [len(folders) for _, folders in seen] == [1, 2, 3]
    assert [line.split()[0] for line, _ in seen] == ["[1/3]", "[2/3]", "[3/3]"]
    assert "toy.count=100" in seen[0][0] and [r["toy.count"] for r in rows] == [100, 200, 300]


def test_cli_sweep_exits_non_zero_naming_failed_runs(tmp_path, capsys):
    from evchain import cli

    p = file_sweep(tmp_path)
    p.write_text("base: ../pipes/p.yaml\nvary:\n  refractory.period_us: [100]\n"
                 "  aedat.packet_us: [1000]\nreport: [aedat_writer.events]\n")
    (tmp_path / "data" / "ev.aedat").write_bytes(b"#!AER-DAT2.0\r\n" + bytes(7))  # truncated
    assert cli.main(["sweep", str(p), "--out", str(tmp_path / "out"), "--workers", "1"]) == 2
    captured = capsys.readouterr()
    assert "evchain: error: 2 of 2 runs failed: refractory.period_us=100 [" in captured.err
    assert captured.out.count("FAILED: ") == 2 and "truncated last record" in captured.out


def test_cli_sweep_set(tmp_path, capsys):
    from evchain import cli

    p = file_sweep(tmp_path)  # refractory.period_us: [100, 1000000] on 400 events
    out = tmp_path / "out"
    assert cli.main(["sweep", str(p), "--set", "aedat_writer.path=other.aedat", "--out",
                     str(out), "--workers", "1"]) == 0
    assert "with aedat_writer.path=other.aedat ->" in capsys.readouterr().out
    runs = json.loads((out / "sweep.json").read_text())["rows"]
    assert all((out / r["run"] / "other.aedat").exists() for r in runs)
    # an unknown parameter fails before any run, naming it
    assert cli.main(["sweep", str(p), "--set", "refractory.nope=1", "--out",
                     str(tmp_path / "bad"), "--workers", "1"]) != 0
    assert "refractory.nope" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_lookup_reads_metrics_and_the_runs_cpu():
    from evchain.sweep import lookup

    report = {"metrics": {"foe": {"dx_mean_px": 1.5}},
              "cpu": {"cpu_s_per_simulated_s": 0.25, "after": "emulator"}}
    assert lookup(report, "foe.dx_mean_px") == 1.5
    assert lookup(report, "cpu.cpu_s_per_simulated_s") == 0.25
    assert lookup(report, "foe.missing") is None
    assert lookup({"metrics": {}}, "cpu.cpu_s_per_simulated_s") is None


def test_one_pipeline_as_two_bases_with_their_own_overrides(tmp_path, registry):
    p = write(tmp_path, "bases:\n  one: {file: base.yaml, set: [toy_source.packets=1]}\n"
                        "  three: {file: base.yaml, set: [toy_source.packets=3]}\n"
                        "report: [toy.count]\n"
                        "cells:\n  plain: []\n  few: [toy_source.events_per_packet=2]\n")
    sweep = load_sweep(p)
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert [(r["variation"], r["base"], r["toy.count"]) for r in rows] == [
        ("plain", "one", 100), ("plain", "three", 300), ("few", "one", 2), ("few", "three", 6)]
    bad = write(tmp_path, "bases:\n  a: {file: base.yaml, set: [nope.x=1]}\ncells: {c: []}\n")
    with pytest.raises(ConfigError, match="base a: override 'nope.x=1' addresses no stage"):
        run_sweep(load_sweep(bad), tmp_path / "out2", workers=1, registry=registry,
                  echo=lambda s: None)
