"""evchain-dv live streams on localhost: ``dv_network`` against dv-processing's own
``NetworkWriter``, ``dv_network_server`` against its own ``NetworkReader``, event for event
(x, y, t, polarity), evchain between the two, Ctrl-C, and bad servers.

Servers get free ports; every wait has a timeout and ends on what it waits for (the one idle
timeout under test aside)."""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

dv = pytest.importorskip("dv_processing")

from evchain.bench import cut_every  # noqa: E402
from evchain.core.filter import Context, Filter, FilterParams  # noqa: E402
from evchain.core.packets import EventPacket, Geometry  # noqa: E402
from evchain.errors import ConfigError, DataError, RunInterrupted  # noqa: E402
from evchain.testing.contract import run_source  # noqa: E402
from evchain.testing.synthetic import random_events  # noqa: E402

from evchain_dv.aedat4 import Aedat4Source  # noqa: E402
from evchain_dv.bench import write_file  # noqa: E402
from evchain_dv.network import DvNetworkServer, DvNetworkSource  # noqa: E402

GEOMETRY = Geometry(346, 260)
T0 = 1_700_000_000_000_000  # DV sends absolute Unix time in µs
WAIT_S = 60.0  # the longest any step may take on a loaded machine
WRITER = Path(__file__).with_name("dv_writer.py")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def events(n: int, seed: int = 1, span: int = 400_000) -> EventPacket:
    return random_events(n, GEOMETRY, t_start=T0, t_end=T0 + span, seed=seed)


def assert_same_events(got: EventPacket, want: EventPacket) -> None:
    assert len(got) == len(want)
    for c in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(got, c), getattr(want, c), err_msg=c)
        assert getattr(got, c).dtype == getattr(want, c).dtype


def assert_consecutive(packets: list[EventPacket]) -> None:
    for i, p in enumerate(packets):
        p.validate(f"packet {i}")
        if i:
            assert p.t_start == packets[i - 1].t_end


class Lines:
    """A process's stdout lines, read with a timeout."""

    def __init__(self, proc: subprocess.Popen):
        self.q: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [self.q.put(ln) for ln in proc.stdout] + [
            self.q.put(None)], daemon=True).start()

    def next(self) -> str:
        line = self.q.get(timeout=WAIT_S)
        assert line is not None, "the process ended"
        return line.strip()


class DvWriter:
    """dv_writer.py: dv-processing's NetworkWriter in a process of its own, sending ``ev``."""

    def __init__(self, tmp_path: Path, ev: EventPacket, batch: int):
        self.port = free_port()
        np.savez(tmp_path / "ev.npz", t=ev.t, x=ev.x, y=ev.y, p=ev.p)
        self.proc = subprocess.Popen(
            [sys.executable, str(WRITER), str(self.port), str(tmp_path / "ev.npz"), str(batch)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.lines = Lines(self.proc)
        assert self.lines.next() == "listening"

    def go(self) -> None:
        """Start sending."""
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        """End the stream (once the clients have read it all: dv-processing's reader drops
        what it has not read when the server closes)."""
        self.proc.stdin.write("close\n")
        self.proc.stdin.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.proc.stdin.close()
        try:
            self.proc.wait(timeout=WAIT_S)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait(timeout=WAIT_S)


def connect(port: int, **params) -> tuple[DvNetworkSource, Context]:
    src = DvNetworkSource()
    src.id = src.name
    ctx = Context(out_dir=Path("."))
    params = {"idle_timeout_s": WAIT_S, **params}  # a safety net: no test waits forever
    src.setup(DvNetworkSource.Params(port=port, **params), ctx)
    return src, ctx


class Receiving:
    """The source's packets, collected in a thread until the stream ends."""

    def __init__(self, src: DvNetworkSource):
        self.packets: list[EventPacket] = []
        self.src = src
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            for p in self.src.packets():
                self.packets.append(p)
        finally:
            self.src.close()

    def wait_for(self, n: int) -> None:
        deadline = time.monotonic() + WAIT_S
        while sum(len(p) for p in list(self.packets)) < n and time.monotonic() < deadline:
            time.sleep(0.005)

    def join(self) -> list[EventPacket]:
        self.thread.join(timeout=WAIT_S)
        assert not self.thread.is_alive(), "the source did not see the end of the stream"
        return self.packets


@pytest.mark.parametrize("batch", [1, 977, 20_000])
def test_source_gets_every_event_of_dv_processing_writer(tmp_path, batch):
    """Until the server ends the stream, as delivered (the events of the last microsecond
    come at the end: more could have followed at that time)."""
    ev = events(20_000 if batch > 1 else 300)
    with DvWriter(tmp_path, ev, batch) as w:
        src, ctx = connect(w.port)  # connected before the writer starts: nothing is missed
        receiving = Receiving(src)
        w.go()
        assert w.lines.next() == f"sent {len(ev)}"
        receiving.wait_for(len(ev) - np.sum(ev.t == ev.t[-1]))
        w.close()
        packets = receiving.join()
    assert ctx.geometry == GEOMETRY  # from the stream's resolution
    assert_same_events(EventPacket.concat(packets), ev)
    assert_consecutive(packets)
    assert len(packets[-1]) == np.sum(ev.t == ev.t[-1])
    if batch == 977:  # a packet per batch as delivered, and the last microsecond's events
        assert len(packets) == -(-len(ev) // batch) + 1
    assert packets[0].t_start == ev.t[0] and packets[-1].t_end == ev.t[-1] + 1


class FakeReader:
    """dv-processing's reader as the source sees it, delivering given batches, then closed."""

    class Batch:
        def __init__(self, a):
            self.a = a

        def __len__(self):
            return len(self.a)

        def numpy(self):
            return self.a

    def __init__(self, batches: list[np.ndarray]):
        self.batches = [self.Batch(a) for a in batches]

    def getNextEventBatch(self):
        return self.batches.pop(0) if self.batches else None

    def isRunning(self):
        return bool(self.batches)


def as_delivered(ev: EventPacket, cuts: list[int]) -> list[EventPacket]:
    """The source's packets for ``ev`` arriving in batches cut at ``cuts``."""
    a = np.zeros(len(ev), [("timestamp", "<i8"), ("x", "<i2"), ("y", "<i2"), ("polarity", "i1")])
    a["timestamp"], a["x"], a["y"], a["polarity"] = ev.t, ev.x, ev.y, ev.p > 0
    edges = [0, *sorted(set(cuts)), len(ev)]
    src = DvNetworkSource()
    batches = [a[i:j] for i, j in zip(edges[:-1], edges[1:], strict=True)]
    src.where, src.reader = "fake", FakeReader(batches)
    src.params = DvNetworkSource.Params(port=1)
    src.context = Context(geometry=GEOMETRY)
    return list(src.packets())


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 300), max_size=12))
def test_as_delivered_keeps_every_event_in_consecutive_slices(cuts):
    ev = events(300, seed=10, span=2_000)  # many events share a microsecond
    packets = as_delivered(ev, cuts)
    assert_same_events(EventPacket.concat(packets), ev)
    assert_consecutive(packets)
    assert packets[0].t_start == ev.t[0] and packets[-1].t_end == ev.t[-1] + 1
    # a packet as soon as its batch came: it ends at that batch's last time
    edges = [0, *sorted(set(cuts)), len(ev)]
    ends = {int(ev.t[j - 1]) for i, j in zip(edges[:-1], edges[1:], strict=True) if j > i}
    assert all(p.t_end in ends for p in packets[:-1])


def test_as_delivered_holds_the_events_of_a_batchs_last_microsecond():
    t = np.array([5, 7, 7, 7, 9, 9, 12], np.int64)
    ev = EventPacket(geometry=GEOMETRY, t_start=5, t_end=13, x=np.arange(7, dtype=np.uint16),
                     y=np.zeros(7, np.uint16), t=t, p=np.array([1, -1] * 3 + [1], np.int8))
    packets = as_delivered(ev, [2, 3, 5])  # [5 7] [7] [7 9] [9 12]
    assert [(p.t_start, p.t_end, p.t.tolist()) for p in packets] == [
        (5, 7, [5]), (7, 9, [7, 7, 7]), (9, 12, [9, 9]), (12, 13, [12])]
    assert_same_events(EventPacket.concat(packets), ev)
    assert as_delivered(ev.select(slice(0, 0)), []) == []


def test_source_cuts_slices_of_packet_us_and_ends_when_idle(tmp_path):
    ev = events(5000, seed=2)
    with DvWriter(tmp_path, ev, 700) as w:
        src, _ = connect(w.port, packet_us=10_000, idle_timeout_s=1.0)
        w.go()
        try:
            packets = list(src.packets())  # the stream stays open: ends 1 s after the last data
        finally:
            src.close()
        w.close()
    assert_same_events(EventPacket.concat(packets), ev)
    assert_consecutive(packets)
    assert packets[0].t_start == ev.t[0] and packets[-1].t_end == ev.t[-1] + 1
    assert all(p.t_end - p.t_start == 10_000 for p in packets[:-1])


def dv_read(port: int, n: int, got: list, info: dict) -> None:
    """dv-processing's reader: connect, read ``n`` events (at most ``WAIT_S``), disconnect."""
    reader = dv.io.NetworkReader("127.0.0.1", port)
    info.update(resolution=reader.getEventResolution(), camera=reader.getCameraName())
    deadline = time.monotonic() + WAIT_S
    while sum(map(len, got)) < n and time.monotonic() < deadline:
        batch = reader.getNextEventBatch()
        if batch is not None:
            got.append(batch.numpy())
        else:
            time.sleep(1e-4)


def read_file(path: Path) -> EventPacket:
    packets, _ = run_source(Aedat4Source, {"path": str(path)}, path.parent)
    return EventPacket.concat(packets)


def as_packet(arrays: list[np.ndarray]) -> EventPacket:
    a = np.concatenate(arrays)
    return EventPacket(geometry=GEOMETRY, t_start=int(a["timestamp"][0]),
                       t_end=int(a["timestamp"][-1]) + 1, x=a["x"].astype(np.uint16),
                       y=a["y"].astype(np.uint16), t=a["timestamp"].astype(np.int64),
                       p=np.where(a["polarity"] > 0, 1, -1).astype(np.int8))


def test_server_sends_every_event_to_dv_processing_reader(tmp_path):
    ev = events(20_000, seed=3)
    packets = cut_every(ev, 7_000)
    port = free_port()
    sink = DvNetworkServer()
    sink.id = sink.name
    ctx = Context(out_dir=tmp_path, geometry=GEOMETRY)
    params = DvNetworkServer.Params(port=port, camera="evchain-test", wait_for_clients=1,
                                    timeout_s=WAIT_S, linger_s=WAIT_S)
    sink.setup(params, ctx)  # listens from here
    got: list[np.ndarray] = []
    info: dict = {}
    t = threading.Thread(target=dv_read, args=(port, len(ev), got, info), daemon=True)
    t.start()
    try:
        for p in packets:  # the first waits for the reader to connect
            assert sink.process(p) is p  # passed on unchanged
        sink.flush()  # the last packets leave; it lingers until the reader has gone
        t.join(timeout=WAIT_S)
        assert not t.is_alive()
    finally:
        sink.close()
    assert info == {"resolution": (346, 260), "camera": "evchain-test"}
    assert_same_events(as_packet(got), ev)
    assert ctx.warnings == []
    assert len(got) == sum(1 for p in packets if len(p))  # one stream packet per evchain packet


def test_server_keeps_the_filter_contract(filter_contract):
    """A pass-through stage: the packets come out as they went in, whatever the cuts (each
    run serves on the same port, one after the other). The source streams live data and
    cannot replay, so it has no contract check."""
    packets = cut_every(events(1500, seed=6), 9_000)
    out = filter_contract.check_filter(DvNetworkServer, {"port": free_port(), "linger_s": 0},
                                       packets)
    np.testing.assert_array_equal(out["t"], EventPacket.concat(packets).t)


def test_evchain_between_two_pipelines(tmp_path):
    """A file replayed by one ``evchain run`` to a server, a second ``evchain run`` receiving it
    into a file: the same events at the end. The server waits for its client (the client's
    connection check before it connects does not start the stream early); the client ends 3 s
    after the last events, and the server, lingering while it is connected, with it."""
    import evchain
    from evchain.core.chain import run_pipeline
    from evchain.core.config import pipeline_from_text
    from evchain.core.registry import make_registry

    ev = events(30_000, seed=4)
    src = write_file(tmp_path / "in.aedat4", cut_every(ev, 10_000))
    port = free_port()
    serve = tmp_path / "serve.yaml"
    serve.write_text(textwrap.dedent(f"""\
        name: replay-to-network
        chain:
          - use: aedat4
            path: {src}
          - use: dv_network_server
            port: {port}
            wait_for_clients: 1
            timeout_s: {WAIT_S}
            linger_s: {WAIT_S}
        """))
    done: list = []
    server = threading.Thread(target=lambda: done.append(
        evchain.run(serve, out_dir=tmp_path / "served")))
    server.start()
    receive_yaml = textwrap.dedent(f"""\
        name: network-to-file
        chain:
          - use: dv_network
            port: {port}
            connect_timeout_s: {WAIT_S}
            idle_timeout_s: 3
          - use: aedat4_writer
            path: got.aedat4
        """)
    registry = make_registry()
    spec = pipeline_from_text(receive_yaml, "receive.yaml", registry)
    report = run_pipeline(spec, registry, tmp_path / "received").report
    server.join(timeout=WAIT_S)
    assert not server.is_alive() and done[0]["status"] == "ok"
    assert report["status"] == "ok" and report["filters"][0]["events_out"] == len(ev)
    assert_same_events(read_file(tmp_path / "received" / "got.aedat4"), ev)


class Watch(Filter):
    """Tells the test when it is set up (after the source: connected), and once ``events``
    events have passed (then the source waits for more)."""

    name = "test_watch"
    consumes = EventPacket
    set_up = threading.Event()
    seen_all = threading.Event()

    class Params(FilterParams):
        events: int

    def setup(self, params, context):
        super().setup(params, context)
        Watch.set_up.set()

    def reset(self):
        self.count = 0

    def process(self, packet):
        self.count += len(packet)
        if self.count >= self.params.events:
            Watch.seen_all.set()
        return packet


class _TestFilters:
    from evchain import hookimpl

    @hookimpl
    def evchain_filters(self):
        return [Watch]


def test_ctrl_c_ends_a_live_stream_with_complete_outputs(tmp_path):
    """The server keeps the stream open; Ctrl-C while the source waits for more ends the run,
    and the file holds every event received (those of the last microsecond, which the source
    held back in case more came at that time, too)."""
    from evchain.core.chain import run_pipeline
    from evchain.core.config import pipeline_from_text
    from evchain.core.registry import make_registry

    ev = events(8000, seed=5)
    registry = make_registry(plugins=(_TestFilters(),))
    Watch.set_up.clear()
    Watch.seen_all.clear()
    with DvWriter(tmp_path, ev, 1000) as w:
        spec = pipeline_from_text(textwrap.dedent(f"""\
            name: live-until-ctrl-c
            chain:
              - use: dv_network
                port: {w.port}
                idle_timeout_s: {WAIT_S}
              - use: test_watch
                events: {len(ev) - np.sum(ev.t == ev.t[-1])}
              - use: aedat4_writer
                path: live.aedat4
            """), "live.yaml", registry)

        def send_then_ctrl_c():
            if Watch.set_up.wait(timeout=WAIT_S):
                w.go()
            if Watch.seen_all.wait(timeout=WAIT_S):
                os.kill(os.getpid(), signal.SIGINT)  # as Ctrl-C in the terminal

        threading.Thread(target=send_then_ctrl_c, daemon=True).start()
        started = time.monotonic()
        with pytest.raises(RunInterrupted) as info:
            run_pipeline(spec, registry, tmp_path / "live")
        assert time.monotonic() - started < WAIT_S  # ended by Ctrl-C, not by the idle timeout
    report = info.value.result.report
    assert report["status"] == "interrupted"
    assert report["filters"][0]["events_out"] == len(ev)
    assert_same_events(read_file(tmp_path / "live" / "live.aedat4"), ev)
    assert not (tmp_path / "live" / "live.aedat4.partial").exists()


def test_nothing_listening_is_a_clear_error_within_the_timeout():
    port = free_port()
    started = time.monotonic()
    with pytest.raises(DataError, match=rf"127\.0\.0\.1:{port}: no DV event stream within "
                                        r"0\.3 s \(Connection refused\)"):
        connect(port, connect_timeout_s=0.3)
    assert time.monotonic() - started < WAIT_S


@pytest.mark.parametrize("reply", [b"HTTP/1.1 400 Bad Request\r\n\r\n", b""])
def test_a_server_that_is_not_dv_is_a_clear_error_not_a_hang(reply):
    """dv-processing's reader would wait for a stream header forever, holding the GIL."""
    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen()
        port = srv.getsockname()[1]
        conns = []

        def serve():
            c, _ = srv.accept()
            conns.append(c)
            c.sendall(reply)

        t = threading.Thread(target=serve, daemon=True)
        t.start()
        want = "got b'HTTP/1.1 400" if reply else r"received nothing within 0\.5 s"
        with pytest.raises(DataError, match=rf":{port}: not a DV \(AEDAT 4\) network stream.*"
                                            f"{want}"):
            connect(port, connect_timeout_s=0.5)
        t.join(timeout=WAIT_S)
        for c in conns:
            c.close()


def test_server_errors(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        sink = DvNetworkServer()
        with pytest.raises(ConfigError, match=rf"cannot serve on 127\.0\.0\.1:{port}: .*"
                                              "(in use|bind)"):
            sink.setup(DvNetworkServer.Params(port=port),
                       Context(out_dir=tmp_path, geometry=GEOMETRY))
        sink.close()
    sink = DvNetworkServer()
    sink.setup(DvNetworkServer.Params(port=free_port(), wait_for_clients=1, timeout_s=0.3),
               Context(out_dir=tmp_path, geometry=GEOMETRY))
    try:
        with pytest.raises(DataError, match=r"1 client\(s\) expected, not connected within "
                                            r"0\.3 s"):
            sink.process(events(10))
    finally:
        sink.close()
    assert sink.server is None


def test_registered_through_the_entry_point():
    from evchain.core.registry import make_registry

    info = make_registry().filters
    assert info["dv_network"].distribution == "evchain-dv"
    assert info["dv_network_server"].distribution == "evchain-dv"


@pytest.mark.parametrize("sender,receiver", [("evchain", "evchain"), ("plain", "dv"),
                                             ("prebuilt", "evchain"), ("prebuilt", "dv")])
def test_benchmark_runs_deliver_every_event(tmp_path, sender, receiver):
    """The runs behind the ``dv-network`` rows, small: nothing lost or changed."""
    from evchain_dv import bench_network

    ev = events(3000, seed=7)
    path = bench_network._save(ev, tmp_path)
    rate, errors, _ = bench_network._measure(sender, receiver, ev, path, 700, 0.0)
    assert errors == 0 and 0 < rate.seconds < WAIT_S and 0 < rate.events < len(ev)


@pytest.mark.parametrize("sender,receiver", [("evchain", "evchain"), ("plain", "dv")])
def test_benchmark_latency_runs(tmp_path, sender, receiver):
    from evchain_dv import bench_network

    ev = events(2000, seed=8)
    path = bench_network._save(ev, tmp_path)
    _, errors, latency = bench_network._measure(sender, receiver, ev, path, 500, 1e-3)
    assert errors == 0 and len(latency) == len(ev)
    assert latency.min() >= 0  # received after it was sent, on one clock


def test_benchmark_error_counts_lost_and_changed_events():
    from evchain_dv.bench_network import _errors

    ev = events(100, seed=9)
    cols = [ev.x.copy(), ev.y.copy(), ev.t.copy(), ev.p.copy()]
    assert _errors(cols, ev, times=True) == 0
    cols[3][5] = -cols[3][5]
    cols[2][7] += 1
    assert _errors(cols, ev, times=True) == 2
    assert _errors(cols, ev, times=False) == 1  # times are the sender's stamps: order only
    assert _errors([c[:90] for c in cols], ev, times=True) == 10 + 2


PIPELINES = sorted((Path(__file__).resolve().parents[1] / "pipelines").glob("*.yaml"))


@pytest.mark.parametrize("path", PIPELINES, ids=[p.name for p in PIPELINES])
def test_plugin_pipelines_validate(path):
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    spec = load_pipeline(path, make_registry())
    assert spec.stages[0].cls.is_source()
    assert {"dv_network", "dv_network_server"} & {s.use for s in spec.stages}
