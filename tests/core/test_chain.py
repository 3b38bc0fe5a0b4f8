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
