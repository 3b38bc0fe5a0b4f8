import json

import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.errors import FilterError
from tests.core import toy_filters

PIPE = """\
name: chain-test
seed: 4
chain:
  - use: toy_source
    packets: 3
  - use: toy_writer
    path: out/count.txt
  - use: toy_flow
"""


def run(text, registry, tmp_path, overrides=()):
    spec = pipeline_from_text(text, "p.yaml", registry, list(overrides))
    return run_pipeline(spec, registry, tmp_path)


def test_report_and_outputs(registry, tmp_path):
    result = run(PIPE, registry, tmp_path)
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["status"] == "ok" and rep["seed"] == 4
    assert rep["pipeline"]["chain"][2]["gain"] == 1.0
    assert set(rep["versions"]) >= {"evchain", "python", "numpy", "numba", "plugins"}
    assert [f["name"] for f in rep["filters"]] == ["toy_source", "toy_writer", "toy_flow"]
    assert rep["filters"][0]["events_out"] == 300 and rep["filters"][1]["unit_in"] == "events"
    assert rep["filters"][1]["events_in"] == 300 and rep["filters"][2]["events_out"] == 300
    assert all(f["wall_s"] >= 0 and f["cpu_s"] >= 0 for f in rep["filters"])
    cpu = rep["cpu"]  # no sensor stage: the stages after the source
    assert cpu["after"] == "toy_source" and cpu["simulated_s"] == pytest.approx(0.03)
    assert cpu["cpu_s"] == pytest.approx(sum(f["cpu_s"] for f in rep["filters"][1:]))
    assert cpu["cpu_s_per_simulated_s"] == pytest.approx(cpu["cpu_s"] / 0.03)
    assert rep["metrics"] == {"toy": {"count": 300}}
    assert (tmp_path / "out" / "count.txt").read_text() == "300"
    assert (tmp_path / "pipeline.resolved.yaml").exists()
    assert result.report == rep


def test_cpu_counts_the_stages_after_the_sensor(registry, tmp_path, monkeypatch):
    monkeypatch.setattr(toy_filters.ToyWriter, "sensor", True)
    rep = run(PIPE, registry, tmp_path).report
    assert rep["cpu"]["after"] == "toy_writer"
    assert rep["cpu"]["cpu_s"] == rep["filters"][2]["cpu_s"]
    assert rep["cpu"]["stages"] == ["toy_flow"]
    monkeypatch.setattr(toy_filters.ToyFlow, "scorer", True)   # scorers are left out
    rep = run(PIPE, registry, tmp_path).report
    assert rep["cpu"]["stages"] == [] and rep["cpu"]["cpu_s"] == 0


def test_failure_closes_all_and_leaves_no_complete_output(registry, tmp_path):
    toy_filters.CLOSED.clear()
    with pytest.raises(FilterError, match=r"filter 'toy_writer' \(toy_writer\) failed in process "
                                          r"on the slice \[0, 10000\) us: RuntimeError: disk"):
        run(PIPE, registry, tmp_path, ["toy_writer.fail=true"])
    assert toy_filters.CLOSED == ["toy_source", "toy_writer"]
    assert not (tmp_path / "out" / "count.txt").exists()
    assert (tmp_path / "out" / "count.txt.partial").exists()
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["status"] == "failed" and "disk on fire" in rep["error"]


def test_source_failure_named(registry, tmp_path):
    with pytest.raises(FilterError, match="filter 'toy_source' .* failed in packets: ValueError"):
        run(PIPE, registry, tmp_path, ["toy_source.fail_at_packet=1"])


def test_series_written_as_csv(registry, tmp_path):
    text = "chain:\n  - use: toy_source\n  - use: toy_cut_dependent\n"
    result = run(text, registry, tmp_path)
    lines = (tmp_path / "series" / "count.csv").read_text().splitlines()
    assert lines == ["t,n", "0,100", "10000,100", "20000,100"]
    assert result.report["series"] == {"count": 3}



def test_scorers_with_ids_keep_their_own_metrics(registry, tmp_path):
    text = ("chain:\n  - use: toy_source\n  - use: toy_scorer\n"
            "  - use: toy_scorer\n    id: second\n    weight: 2\n")
    rep = run(text, registry, tmp_path).report
    assert rep["metrics"] == {"scored": {"count": 300}, "scored@second": {"count": 600}}


def test_a_run_first_marks_its_folder_and_removes_what_it_will_write(registry, tmp_path):
    """An earlier run's ok report, series and outputs must not survive beside a run that
    fails in setup: the folder is marked running first and they are removed."""
    text = ("chain:\n  - use: toy_source\n  - use: toy_writer\n    path: out/count.txt\n"
            "  - use: toy_cut_dependent\n")
    run(text, registry, tmp_path)
    assert (tmp_path / "series" / "count.csv").exists()
    assert (tmp_path / "out" / "count.txt").exists()
    (tmp_path / "series" / "other.csv").write_text("t\n1\n")  # a series of yet another run
    (tmp_path / "out" / "count.txt.partial").write_text("old")
    (tmp_path / "mine.txt").write_text("the user's")          # not this run's: kept
    with pytest.raises(FilterError, match="boom"):
        run(text, registry, tmp_path, ["toy_source.fail_at_packet=0"])
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["status"] == "failed"
    assert not list((tmp_path / "series").iterdir())
    assert not (tmp_path / "out" / "count.txt").exists()
    # the writer's own partial file of this run, not the earlier one
    assert (tmp_path / "out" / "count.txt.partial").read_text() == ""
    assert (tmp_path / "mine.txt").exists()


def test_report_says_running_while_the_run_is_under_way(registry, tmp_path):
    seen = []

    class Spy(toy_filters.ToyScorer):
        name = "toy_spy"

        def process(self, packet):
            seen.append(json.loads((tmp_path / "report.json").read_text())["status"])
            return packet

    from evchain.core.registry import make_registry

    reg = make_registry(discover=False, plugins=(toy_filters, _Plugin(Spy)))
    run("chain:\n  - use: toy_source\n  - use: toy_spy\n", reg, tmp_path)
    assert seen == ["running"] * 3
    assert json.loads((tmp_path / "report.json").read_text())["status"] == "ok"


class _Plugin:
    def __init__(self, cls):
        self.cls = cls

    @toy_filters.hookimpl
    def evchain_filters(self):
        return [self.cls]


def test_declared_output_folders_and_derived_files_are_removed(tmp_path):
    from evchain.core.chain import start_run_folder
    from evchain.core.registry import make_registry

    text = ("chain:\n  - use: toy_source\n  - use: toy_flow\n  - use: flow_image\n"
            "    path: f.png\n    times_us: [10000, 20000]\n    duration_us: 5000\n"
            "    save_npz: kept.npz\n")
    reg = make_registry(discover=True, plugins=(toy_filters,))
    spec = pipeline_from_text(text, "p.yaml", reg)
    old = ["f_10000us.png", "f_20000us.png", "kept.npz", "kept.npz.partial"]
    for name in [*old, "f_30000us.png"]:
        (tmp_path / name).write_text("old")
    start_run_folder(spec, tmp_path, {})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f_30000us.png", "report.json"]


def test_killed_run_leaves_a_running_report_and_no_old_outputs(tmp_path):
    """SIGKILL cannot be caught: what is left must still not look like success."""
    import os
    import signal
    import subprocess
    import sys
    import time

    p = tmp_path / "p.yaml"
    p.write_text("chain:\n  - use: scene\n    width: 64\n    height: 48\n    supersample: 1\n"
                 "    start_m: 240\n    duration_s: 0.02\n  - use: emulator\n"
                 "  - use: aedat_writer\n")
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "evchain", "run", str(p), "--out", str(out), "--no-progress"]
    subprocess.run(cmd, check=True, capture_output=True)
    assert json.loads((out / "report.json").read_text())["status"] == "ok"
    assert (out / "events.aedat").exists()
    long = cmd + ["--set", "scene.duration_s=1.5"]
    proc = subprocess.Popen(long, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        # the writer's .partial file exists once the run is past its start (report marked
        # running, old outputs removed) and before it can finish
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / "events.aedat.partial").exists():
                break
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL  # killed while it ran, not finished
    assert json.loads((out / "report.json").read_text())["status"] == "running"
    assert not (out / "events.aedat").exists()
