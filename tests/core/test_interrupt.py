"""Ctrl-C (SIGINT) during a run: the first stops the stream and finishes cleanly (every filter
flushed and closed, outputs complete up to there), a second one aborts."""

import json
import signal
import threading

import pytest
from pydantic import Field

from evchain import cli
from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.registry import make_registry
from evchain.errors import RunInterrupted
from tests.core import toy_filters

STREAM_ENDED: list[str] = []  # sources whose packets() generator finished or was closed


def ctrl_c(context, times: int = 1) -> None:
    """SIGINT, as from Ctrl-C. Its handler runs on the main thread; a source runs on a thread of
    its own, so it waits here until the first signal was handled, as a source that is busy
    while the user presses Ctrl-C would see it."""
    signal.raise_signal(signal.SIGINT)
    assert context.stop.wait(10)
    for _ in range(times - 1):
        signal.raise_signal(signal.SIGINT)


class SigintSource(toy_filters.ToySource):
    """Random events in packets of 10 ms; sends SIGINT (Ctrl-C) to this process on request."""

    name = "toy_sigint"

    class Params(toy_filters.ToySource.Params):
        sigint_at_packet: int | None = Field(None, description="send SIGINT before this packet")
        sigints: int = Field(1, ge=1, description="how many SIGINTs, one after the other")
        checks_stop: bool = Field(False, description="return once context.stop is set, as a "
                                  "live source does while it waits")

    def packets(self):
        try:
            for i in range(self.params.packets):
                if i == self.params.sigint_at_packet:
                    ctrl_c(self.context, self.params.sigints)
                if self.params.checks_stop and self.context.stop.is_set():
                    return
                yield toy_filters.random_events(self.params.events_per_packet,
                                                self.context.geometry, i * 10_000,
                                                (i + 1) * 10_000, seed=i)
        finally:
            STREAM_ENDED.append(self.id)


class Holding(toy_filters.ToySource):
    """A live source: it watches ``context.stop`` and then hands over what it holds."""

    name = "toy_holding"
    ends_on_stop = True
    Params = SigintSource.Params

    def packets(self):
        g = self.context.geometry
        for i in range(self.params.packets):
            if i == self.params.sigint_at_packet:
                ctrl_c(self.context)
            if self.context.stop.is_set():
                yield toy_filters.random_events(7, g, i * 10_000, i * 10_000 + 1, seed=i)
                return
            yield toy_filters.random_events(100, g, i * 10_000, (i + 1) * 10_000, seed=i)


class _Plugin:
    @toy_filters.hookimpl
    def evchain_filters(self):
        return [SigintSource, Holding]


@pytest.fixture
def registry():
    return make_registry(discover=False, plugins=(toy_filters, _Plugin()))


PIPE = """\
name: interrupt-test
chain:
  - use: toy_sigint
    packets: 5
  - use: toy_writer
    path: out/count.txt
  - use: toy_scorer
  - use: toy_cut_dependent
"""


def run(registry, tmp_path, overrides=()):
    spec = pipeline_from_text(PIPE, "p.yaml", registry, list(overrides))
    return run_pipeline(spec, registry, tmp_path)


def test_first_ctrl_c_flushes_every_filter_and_writes_complete_outputs(registry, tmp_path):
    toy_filters.CLOSED.clear()
    STREAM_ENDED.clear()
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(RunInterrupted, match=r"at 30000 us: every filter was flushed") as info:
        run(registry, tmp_path, ["toy_sigint.sigint_at_packet=2"])
    assert signal.getsignal(signal.SIGINT) is handler  # restored
    # packets 0, 1 and the one in flight (2) went through the chain, nothing after
    assert (tmp_path / "out" / "count.txt").read_text() == "300"
    assert not (tmp_path / "out" / "count.txt.partial").exists()
    assert (tmp_path / "series" / "count.csv").read_text().splitlines() == [
        "t,n", "0,100", "10000,100", "20000,100"]
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["status"] == "interrupted" and "30000 us" in rep["error"]
    assert rep["metrics"] == {"toy": {"count": 300}, "scored": {"count": 300}}  # flushed
    assert rep["filters"][0]["events_out"] == 300
    assert info.value.result.report == rep and info.value.t_us == 30_000
    assert STREAM_ENDED == ["toy_sigint"]  # the source's generator was closed
    assert toy_filters.CLOSED == ["toy_sigint", "toy_writer"]
    assert isinstance(info.value, KeyboardInterrupt)  # callers stop as on Ctrl-C


def test_second_ctrl_c_aborts_and_completes_nothing(registry, tmp_path):
    toy_filters.CLOSED.clear()
    with pytest.raises(KeyboardInterrupt) as info:
        run(registry, tmp_path, ["toy_sigint.sigint_at_packet=2", "toy_sigint.sigints=2"])
    assert not isinstance(info.value, RunInterrupted)
    assert not (tmp_path / "out" / "count.txt").exists()
    assert (tmp_path / "out" / "count.txt.partial").exists()
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["status"] == "failed" and rep["error"].startswith("KeyboardInterrupt")
    assert toy_filters.CLOSED == ["toy_sigint", "toy_writer"]


def test_a_source_that_checks_stop_ends_at_once(registry, tmp_path):
    """A live source checks ``context.stop`` while it waits: no packet after the Ctrl-C."""
    with pytest.raises(RunInterrupted, match="at 20000 us"):
        run(registry, tmp_path, ["toy_sigint.sigint_at_packet=2", "toy_sigint.checks_stop=true"])
    assert (tmp_path / "out" / "count.txt").read_text() == "200"
    with pytest.raises(RunInterrupted, match="before the first packet"):
        run(registry, tmp_path, ["toy_sigint.sigint_at_packet=0", "toy_sigint.checks_stop=true"])
    # nothing came: empty but complete outputs
    assert (tmp_path / "out" / "count.txt").read_text() == "0"
    assert json.loads((tmp_path / "report.json").read_text())["status"] == "interrupted"


def test_a_source_that_ends_on_stop_hands_over_what_it_holds(registry, tmp_path):
    text = PIPE.replace("toy_sigint", "toy_holding")
    spec = pipeline_from_text(text, "p.yaml", registry, ["toy_holding.sigint_at_packet=2"])
    with pytest.raises(RunInterrupted, match="at 20001 us"):
        run_pipeline(spec, registry, tmp_path)
    assert (tmp_path / "out" / "count.txt").read_text() == "207"


def test_without_ctrl_c_nothing_changes(registry, tmp_path):
    result = run(registry, tmp_path)
    assert result.report["status"] == "ok" and result.report["error"] is None
    assert (tmp_path / "out" / "count.txt").read_text() == "500"


def test_runs_outside_the_main_thread(registry, tmp_path):
    """Signal handlers can only be set in the main thread: elsewhere a run is unchanged."""
    got = []
    t = threading.Thread(target=lambda: got.append(run(registry, tmp_path).report["status"]))
    t.start()
    t.join(timeout=60)
    assert got == ["ok"]


def test_cli_exits_130_after_writing_the_outputs(registry, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli, "_registry", lambda: registry)
    pipe = tmp_path / "p.yaml"
    pipe.write_text(PIPE)
    out = tmp_path / "run"
    rc = cli.main(["run", str(pipe), "--out", str(out), "--no-progress",
                   "--set", "toy_sigint.sigint_at_packet=1"])
    assert rc == 130
    captured = capsys.readouterr()
    assert "interrupt-test: stopped after" in captured.out
    assert "toy_writer" in captured.out  # the per-stage table is still printed
    assert "evchain: interrupted (Ctrl-C) at 20000 us" in captured.err
    assert (out / "out" / "count.txt").read_text() == "200"
