"""The run's progress bar: simulated seconds, and a notice while numba compiles kernels."""

import io
import logging

import numba
import numpy as np

from evchain.core import progress as progress_module
from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.progress import COMPILING, RunProgress
from evchain.core.registry import make_registry
from tests.core import toy_filters


class FakeTerminal(io.StringIO):
    def isatty(self):
        return True


def test_bar_counts_simulated_seconds(monkeypatch):
    term = FakeTerminal()
    monkeypatch.setattr("sys.stderr", term)
    bar = RunProgress("scene", (0, 2_000_000), bar=True)
    bar.update(500_000)
    bar.bar.refresh()
    shown = term.getvalue()
    bar.close()
    assert "0.50/2.00 s simulated" in shown and "25%" in shown
    assert "us/s" not in shown and "kus" not in shown


def test_compiling_is_announced_and_left_out_of_the_rate(monkeypatch, caplog):
    term = FakeTerminal()
    monkeypatch.setattr("sys.stderr", term)
    monkeypatch.setattr(progress_module, "_announced", False)
    bar = RunProgress("scene", (0, 1_000_000), bar=True)
    start = bar.bar.start_t
    descriptions = []

    @numba.njit(cache=False)
    def kernel(x):  # a kernel compiled now, as on a first run
        return x * 2 + 1

    real_started = bar.compile_started

    def started():
        real_started()
        descriptions.append(bar.bar.desc)

    monkeypatch.setattr(bar, "compile_started", started)
    with caplog.at_level(logging.INFO, logger="evchain"):
        kernel(np.int64(3))
    assert descriptions and descriptions[0] == COMPILING
    assert bar.bar.desc == "scene"             # back to the source's name afterwards
    assert bar.bar.start_t > start             # the compile time is not counted
    assert any(COMPILING in r.getMessage() for r in caplog.records)
    bar.close()
    kernel(np.int64(4))                        # compiled: no notice, and no listener left
    assert len(descriptions) == 1


def test_run_without_a_bar_logs_compilation_for_debug(tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(progress_module, "_announced", False)
    registry = make_registry(discover=False, plugins=(toy_filters,))
    spec = pipeline_from_text("chain:\n  - use: toy_source\n", "p.yaml", registry)

    @numba.njit(cache=False)
    def late(x):
        return x - 1

    real = toy_filters.ToySource.packets

    def packets(self):
        late(np.float64(1.0))  # compiles while the stream runs
        yield from real(self)

    monkeypatch.setattr(toy_filters.ToySource, "packets", packets)
    with caplog.at_level(logging.DEBUG, logger="evchain"):
        run_pipeline(spec, registry, tmp_path)
    notices = [r for r in caplog.records if COMPILING in r.getMessage()]
    assert [r.levelno for r in notices] == [logging.DEBUG]


def test_bar_asked_for_but_no_terminal_compiles_without_error(monkeypatch):
    """A run with progress on whose stderr is not a terminal (a log file, CI) gets no bar, and
    a kernel compiled meanwhile must not touch one."""
    monkeypatch.setattr("sys.stderr", io.StringIO())
    bar = RunProgress("scene", (0, 1_000_000), bar=True)
    assert bar.bar is None

    @numba.njit(cache=False)
    def kernel(x):
        return x + 3

    assert kernel(np.int64(1)) == 4          # compile_started / compile_ended ran
    bar.update(500_000)
    bar.close()
