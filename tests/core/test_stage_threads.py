"""Stages on threads of their own give the packets of stages in order, end cleanly on errors
and when the consumer stops early, and a chain run gives the same outputs either way."""

import json
import threading
import time

import pytest

from evchain.core import stage_threads
from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.registry import make_registry
from evchain.errors import FilterError
from tests.core import toy_filters


class Add:
    """Adds its number to each packet (a list), remembers the order it saw, and on flush
    emits one packet of its own."""

    def __init__(self, k: int, fail_at: int | None = None, slow_s: float = 0.0):
        self.k, self.fail_at, self.slow_s = k, fail_at, slow_s
        self.seen: list[list[int]] = []
        self.flushed = 0

    def process(self, packet):
        if packet[0] == self.fail_at:
            raise ValueError(f"stage {self.k} failed at {packet[0]}")
        time.sleep(self.slow_s)
        self.seen.append(list(packet))
        return [*packet, self.k]

    def flush(self):
        self.flushed += 1
        return [-self.k]


def packets(n: int):
    return ([i] for i in range(n))


@pytest.mark.parametrize("n_stages", [0, 1, 3])
@pytest.mark.parametrize("n_packets", [0, 1, 13])
def test_threads_give_the_packets_in_order_gives(n_stages, n_packets):
    a = [Add(k) for k in range(1, n_stages + 1)]
    b = [Add(k) for k in range(1, n_stages + 1)]
    got = list(stage_threads.in_threads(packets(n_packets), a))
    want = list(stage_threads.in_order(packets(n_packets), b))
    assert got == want
    assert [s.seen for s in a] == [s.seen for s in b]
    assert all(s.flushed == 1 for s in a + b)
    # every source packet went through every stage, then each flush through the later ones
    assert len(want) == n_packets + n_stages
    if n_stages:
        assert want[-1] == [-n_stages]


def test_more_packets_than_the_queues_hold_and_a_slow_stage():
    n = 5 * stage_threads.DEPTH
    stages = [Add(1), Add(2, slow_s=0.002), Add(3)]
    got = list(stage_threads.in_threads(packets(n), stages))
    assert [p[0] for p in got[:n]] == list(range(n))
    assert all(p[1:] == [1, 2, 3] for p in got[:n])


def _no_stage_threads_left():
    return not [t for t in threading.enumerate() if t.name.startswith("evchain-")]


@pytest.mark.parametrize("failing", [1, 2, 3])
def test_an_error_in_a_stage_reaches_the_consumer_and_every_thread_ends(failing):
    stages = [Add(k, fail_at=7 if k == failing else None) for k in (1, 2, 3)]
    with pytest.raises(ValueError, match=f"stage {failing} failed at 7"):
        list(stage_threads.in_threads(packets(50), stages))
    assert _no_stage_threads_left()
    # nothing after the failing packet reached the stages after the failing one
    for s in stages[failing:]:
        assert [p[0] for p in s.seen] == list(range(7))
        assert s.flushed == 0


def test_an_error_in_the_source_reaches_the_consumer():
    def source():
        yield [0]
        raise OSError("source broke")

    with pytest.raises(OSError, match="source broke"):
        list(stage_threads.in_threads(source(), [Add(1)]))
    assert _no_stage_threads_left()


def test_a_consumer_that_stops_early_ends_every_thread():
    stages = [Add(1), Add(2)]
    gen = stage_threads.in_threads(packets(1000), stages)
    assert next(gen) == [0, 1, 2]
    gen.close()
    assert _no_stage_threads_left()
    assert len(stages[0].seen) < 1000  # the queues are bounded: the source did not run ahead
    assert all(s.flushed == 0 for s in stages)


PIPE = """\
name: threads-test
chain:
  - use: toy_source
    packets: 9
  - use: toy_writer
    path: out/count.txt
  - use: toy_cut_dependent
  - use: toy_scorer
"""


def test_a_chain_gives_the_same_outputs_on_threads_and_in_order(tmp_path):
    registry = make_registry(discover=False, plugins=(toy_filters,))
    reports = {}
    for threads in (True, False):
        out = tmp_path / str(threads)
        spec = pipeline_from_text(PIPE, "p.yaml", registry, [])
        reports[threads] = run_pipeline(spec, registry, out, threads=threads).report
        reports[threads]["files"] = {p.relative_to(out).as_posix(): p.read_bytes()
                                     for p in sorted(out.rglob("*")) if p.is_file()
                                     and p.name != "report.json"}
    a, b = reports[True], reports[False]
    assert a["files"] == b["files"] and a["files"]
    assert a["metrics"] == b["metrics"] and a["metrics"]
    assert a["series"] == b["series"]
    counts = ("events_in", "events_out", "unit_in", "name", "id")
    assert ([{k: f[k] for k in counts} for f in a["filters"]]
            == [{k: f[k] for k in counts} for f in b["filters"]])


def test_a_failing_filter_is_named_with_its_slice_on_threads(tmp_path):
    registry = make_registry(discover=False, plugins=(toy_filters,))
    text = PIPE.replace("  - use: toy_scorer\n", "  - use: toy_writer\n    id: broken\n"
                        "    path: out/broken.txt\n    fail: true\n")
    spec = pipeline_from_text(text, "p.yaml", registry, [])
    with pytest.raises(FilterError, match=r"'broken'.*process on the slice \[0, 10000\) us"):
        run_pipeline(spec, registry, tmp_path)
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["status"] == "failed" and "disk on fire" in rep["error"]
    assert not (tmp_path / "out" / "count.txt").exists()  # the upstream writer's: not complete
    assert _no_stage_threads_left()


def test_a_failing_source_is_named_on_threads(tmp_path):
    registry = make_registry(discover=False, plugins=(toy_filters,))
    spec = pipeline_from_text(PIPE, "p.yaml", registry, ["toy_source.fail_at_packet=4"])
    with pytest.raises(FilterError, match=r"'toy_source'.*failed in packets"):
        run_pipeline(spec, registry, tmp_path)
    assert not (tmp_path / "out" / "count.txt").exists()
    assert _no_stage_threads_left()


THREADS_SEEN: dict[str, set[int]] = {}


class ThreadAffine(toy_filters.CutDependent):
    """Records the thread of each of its calls, as a filter holding an SQLite connection
    would need them all on one thread."""

    name = "toy_thread_affine"

    def _seen(self):
        THREADS_SEEN.setdefault(self.id, set()).add(threading.get_ident())

    def setup(self, params, context):
        super().setup(params, context)
        self._seen()

    def process(self, packet):
        self._seen()
        return packet

    def flush(self):
        self._seen()

    def close(self):
        self._seen()


class _Plugin:
    @toy_filters.hookimpl
    def evchain_filters(self):
        return [ThreadAffine]


@pytest.mark.parametrize("threads", [True, False])
def test_every_call_of_a_filter_runs_on_one_thread(tmp_path, threads):
    registry = make_registry(discover=False, plugins=(toy_filters, _Plugin()))
    text = PIPE + "  - use: toy_thread_affine\n    id: a\n  - use: toy_thread_affine\n    id: b\n"
    THREADS_SEEN.clear()
    run_pipeline(pipeline_from_text(text, "p.yaml", registry, []), registry, tmp_path,
                 threads=threads)
    assert all(len(seen) == 1 for seen in THREADS_SEEN.values()), THREADS_SEEN
    main = {threading.get_ident()}
    if threads:  # a thread per stage, none of them the caller's
        assert THREADS_SEEN["a"] != THREADS_SEEN["b"] and main not in THREADS_SEEN.values()
    else:
        assert THREADS_SEEN["a"] == THREADS_SEEN["b"] == main


def test_cli_serial_runs_on_one_thread_with_the_same_outputs(tmp_path, monkeypatch):
    from evchain import cli

    registry = make_registry(discover=False, plugins=(toy_filters, _Plugin()))
    monkeypatch.setattr(cli, "_registry", lambda: registry)
    pipe = tmp_path / "p.yaml"
    pipe.write_text(PIPE + "  - use: toy_thread_affine\n    id: a\n")
    files = {}
    for flag in ([], ["--serial"]):
        out = tmp_path / ("serial" if flag else "threads")
        THREADS_SEEN.clear()
        assert cli.main(["run", str(pipe), "--out", str(out), "--no-progress", *flag]) == 0
        on_main = THREADS_SEEN["a"] == {threading.get_ident()}
        assert on_main == bool(flag)
        files[bool(flag)] = {p.relative_to(out).as_posix(): p.read_bytes()
                             for p in sorted(out.rglob("*")) if p.is_file()
                             and p.name != "report.json"}
    assert files[True] == files[False] and "out/count.txt" in files[True]
