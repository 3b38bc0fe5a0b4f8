"""Live stream benchmarks (``evchain bench dv-network``): evchain's ends of a DV network stream
next to plain dv-processing, on localhost TCP, in the same run.

``dv-network`` (throughput, events/s; random events, 346x260, batches of 10 000; 2 M events for
the loopback, 10 M for the receive rows, a quarter with ``--quick``):

* ``dv-network-loopback-evchain``: evchain packets through ``dv_network_server`` to
  ``dv_network``, and ``dv-network-loopback-dv``: a Python program with dv-processing alone
  (``EventStore.push_back`` per event, ``NetworkWriter.writeEvents``; ``NetworkReader`` and
  ``EventStore.numpy()``);
* ``dv-network-receive-evchain`` / ``-dv``: the same receivers, with a sender whose stores are
  filled before the start (only ``writeEvents`` runs, as in a camera driver or DV).

``dv-network-latency`` (µs from sending to receiving, median, p99 and max over every event):
batches of 1 000 events with a 1 ms pause after each, stamped as they start on their way
(:mod:`evchain_dv.bench_sender`); ``-evchain`` and ``-dv`` as for the loopback.

The sender is a process of its own (its ``NetworkWriter``, and for evchain the server process
behind ``dv_network_server``); the receiver runs in the benchmark's process and polls the same
way at both ends (:class:`evchain_dv.network.Poll`). Throughput is the stream's steady rate:
the events that arrive after the first arrival, over the time from it to the last one (which
leaves out starting the sender); ``dv_network`` holds back the events of a batch's last
microsecond until the next batch, so the stream's very last microsecond is not timed. ``error``
counts events lost or changed (x, y, t, polarity against what was sent; the stamped times of
the latency rows only by their order); ``limit_ratio`` of an evchain row: its throughput /
dv-processing's (latency: dv-processing's median / evchain's).
"""

from __future__ import annotations

import os
import queue
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from evchain.bench import BenchRow
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.testing.synthetic import random_events

GEOMETRY = Geometry(346, 260)
BATCH = 10_000
LATENCY_BATCH, LATENCY_PAUSE_S = 1_000, 1e-3
WAIT_S = 300.0  # the longest any step may take
SENDER = Path(__file__).with_name("bench_sender.py")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Sender:
    """The sending process of :mod:`evchain_dv.bench_sender`, ready to start."""

    def __init__(self, kind: str, events_path: Path, batch: int, pause_s: float):
        import evchain

        import evchain_dv

        self.port = free_port()
        roots = [str(Path(m.__file__).parents[1]) for m in (evchain, evchain_dv)]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(roots + [env.get("PYTHONPATH", "")])
        self.proc = subprocess.Popen(
            [sys.executable, str(SENDER), kind, str(self.port), str(events_path), str(batch),
             str(pause_s)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        self.lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        self._expect("ready")

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.strip())
        self.lines.put(None)

    def _expect(self, word: str) -> None:
        try:
            line = self.lines.get(timeout=WAIT_S)
        except queue.Empty:
            line = f"nothing within {WAIT_S:g} s"
        if line is None or not line.startswith(word):
            self.close()
            raise RuntimeError(f"bench sender: expected {word!r}, got {line!r}")

    def say(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.say("close")
                self.proc.wait(timeout=WAIT_S)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(timeout=WAIT_S)


class Rate:
    """The steady rate of a stream: the events that arrive after the first arrival, over the
    time from it to the last one counted (start-up left out)."""

    def __init__(self):
        self.first = self.last = None
        self.events = 0

    def arrived(self, n: int) -> None:
        self.last = time.perf_counter()
        if self.first is None:
            self.first = self.last
        else:
            self.events += n

    @property
    def seconds(self) -> float:
        return self.last - self.first if self.first is not None else np.inf


def _receive_evchain(sender: Sender, n: int) -> tuple[Rate, list[np.ndarray], np.ndarray]:
    """(the rate until ``n`` events arrived, the x, y, t, p columns received, each event's
    arrival in µs of the monotonic clock). ``n``: the events sent but those of the last µs,
    which the source holds until it ends."""
    from evchain_dv.network import DvNetworkSource

    src = DvNetworkSource()
    src.id = src.name
    ctx = Context()
    src.setup(DvNetworkSource.Params(port=sender.port, connect_timeout_s=WAIT_S,
                                     idle_timeout_s=WAIT_S), ctx)
    packets, arrivals, count, rate = [], [], 0, Rate()
    try:
        sender.say("go")
        deadline = time.perf_counter() + WAIT_S
        for p in src.packets():
            arrivals.append(np.full(len(p), time.monotonic_ns() // 1000))
            packets.append(p)
            if count < n:
                rate.arrived(len(p))
            count += len(p)
            if count >= n and not ctx.stop.is_set() or time.perf_counter() > deadline:
                ctx.stop.set()  # the source hands over what it holds, then ends
    finally:
        src.close()
    whole = EventPacket.concat(packets) if packets else EventPacket.empty(GEOMETRY, 0, 0)
    return rate, [whole.x, whole.y, whole.t, whole.p], _cat(arrivals)


def _receive_dv(sender: Sender, n: int) -> tuple[Rate, list[np.ndarray], np.ndarray]:
    import dv_processing as dv

    from evchain_dv.network import Poll

    reader = dv.io.NetworkReader("127.0.0.1", sender.port)
    batches, arrivals, count, poll, rate = [], [], 0, Poll(), Rate()
    sender.say("go")
    deadline = time.perf_counter() + WAIT_S
    while count < n and time.perf_counter() < deadline:
        batch = reader.getNextEventBatch()
        if batch is None:
            if not reader.isRunning():
                break
            poll.idle()
            continue
        poll.data()
        a = batch.numpy()
        arrivals.append(np.full(len(a), time.monotonic_ns() // 1000))
        rate.arrived(len(a))
        batches.append(a)
        count += len(a)
    del reader  # disconnect
    a = np.concatenate(batches) if batches else np.zeros(0, [("timestamp", "i8"), ("x", "i2"),
                                                            ("y", "i2"), ("polarity", "i1")])
    cols = [a["x"].astype(np.uint16), a["y"].astype(np.uint16), a["timestamp"].astype(np.int64),
            np.where(a["polarity"] > 0, 1, -1).astype(np.int8)]
    return rate, cols, _cat(arrivals)


def _cat(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _errors(got: list[np.ndarray], want: EventPacket, times: bool) -> int:
    """Events lost or changed: missing or extra ones, and those that differ (in time only if
    ``times``; otherwise times must not go backwards)."""
    n = min(len(got[0]), len(want))
    cols = [want.x, want.y, want.t, want.p]
    differ = np.zeros(n, bool)
    for k, (g, w) in enumerate(zip(got, cols, strict=True)):
        if k != 2 or times:
            differ |= g[:n] != w[:n]
    if not times:
        differ[1:] |= np.diff(got[2][:n]) < 0
    return abs(len(got[0]) - len(want)) + int(differ.sum())


def _measure(kind: str, receiver: str, events: EventPacket, path: Path, batch: int,
             pause_s: float) -> tuple[Rate, int, np.ndarray]:
    """(the rate, events lost or changed, latencies in µs) of one sender -> receiver run."""
    sender = Sender(kind, path, batch, pause_s)
    try:
        if receiver == "evchain":  # the sent times of the latency rows are one µs apart
            last_us = 1 if pause_s else int(np.sum(events.t == events.t[-1]))
            rate, got, arrived = _receive_evchain(sender, len(events) - last_us)
        else:
            rate, got, arrived = _receive_dv(sender, len(events))
        sender._expect("sent")
    finally:
        sender.close()
    errors = _errors(got, events, times=pause_s == 0)
    return rate, errors, arrived - got[2]


def _save(events: EventPacket, folder: Path) -> Path:
    path = folder / "events.npz"
    np.savez(path, t=events.t, x=events.x, y=events.y, p=events.p)
    return path


def _data(n: int, sender: str, receiver: str) -> str:
    return (f"{n / 1e6:g} M random events 346x260 in batches of {BATCH:,}, 127.0.0.1 TCP; "
            f"{sender} -> {receiver}")


SENDERS = {"evchain": "evchain packets -> dv_network_server",
           "plain": "EventStore.push_back + NetworkWriter",
           "prebuilt": "NetworkWriter (stores filled before the start)"}
RECEIVERS = {"evchain": "dv_network", "dv": "NetworkReader + EventStore.numpy()"}


def dv_network(quick: bool) -> list[BenchRow]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="evchain-bench-dv-") as tmp:
        for name, n, kind, stage_ev, stage_dv in (
                ("loopback", 500_000 if quick else 2_000_000, "plain",
                 "dv_network_server->dv_network", "NetworkWriter->NetworkReader"),
                ("receive", 2_000_000 if quick else 10_000_000, "prebuilt", "dv_network",
                 "NetworkReader")):
            events = random_events(n, GEOMETRY, t_start=0, t_end=n, seed=0)  # 1 event/µs
            path = _save(events, Path(tmp))
            rates = {}
            for receiver in ("evchain", "dv"):
                sender = "evchain" if (name, receiver) == ("loopback", "evchain") else kind
                rate, errors, _ = _measure(sender, receiver, events, path, BATCH, 0.0)
                rates[receiver] = rate.events / rate.seconds
                rows.append(BenchRow(
                    f"dv-network-{name}-{receiver}", stage_ev if receiver == "evchain"
                    else stage_dv, rates[receiver], "events/s", errors,
                    "events lost or changed", None,
                    {"events": n, "timed_events": rate.events, "seconds": rate.seconds,
                     "batch_events": BATCH},
                    data=_data(n, SENDERS[sender], RECEIVERS[receiver])))
            rows[-2].limit_ratio = rates["evchain"] / rates["dv"]
    return rows


def dv_network_latency(quick: bool) -> list[BenchRow]:
    batches = 300 if quick else 2_000
    n = batches * LATENCY_BATCH
    events = random_events(n, GEOMETRY, t_start=0, t_end=n, seed=1)
    rows = []
    with tempfile.TemporaryDirectory(prefix="evchain-bench-dv-") as tmp:
        path = _save(events, Path(tmp))
        medians = {}
        for receiver in ("evchain", "dv"):
            sender = "evchain" if receiver == "evchain" else "plain"
            rate, errors, lat = _measure(sender, receiver, events, path, LATENCY_BATCH,
                                         LATENCY_PAUSE_S)
            p50, p99, top = (float(v) for v in np.percentile(lat, [50, 99, 100]))
            medians[receiver] = p50
            rows.append(BenchRow(
                f"dv-network-latency-{receiver}", "dv_network_server->dv_network"
                if receiver == "evchain" else "NetworkWriter->NetworkReader", p50,
                "us (median latency)", errors, "events lost or changed", None,
                {"latency_p99_us": p99, "latency_max_us": top, "events": n,
                 "batch_events": LATENCY_BATCH, "pause_ms": LATENCY_PAUSE_S * 1e3,
                 "events_per_s": rate.events / rate.seconds},
                data=(f"{batches} batches of {LATENCY_BATCH:,} random events, 346x260, "
                      f"{LATENCY_PAUSE_S * 1e3:g} ms pause after each, 127.0.0.1 TCP; "
                      f"{SENDERS[sender]} -> {RECEIVERS[receiver]}")))
        rows[0].limit_ratio = medians["dv"] / medians["evchain"]
    return rows


WORKLOADS = {"dv-network": dv_network, "dv-network-latency": dv_network_latency}
