"""Live DV event streams over TCP through dv-processing: ``dv_network`` and
``dv_network_server``.

DV (iniVation's software, its "Network TCP server" output) and dv-processing's
``NetworkWriter`` serve an event stream as AEDAT 4 packets over TCP; ``NetworkReader`` reads
one. The stream format is dv-processing's business; this module converts its event stores to
and from evchain packets (time in µs as sent, polarity ``True``/``False`` as ``+1``/``-1``, the
stream's resolution as the sensor size) and makes both ends behave in a chain:

* ``dv_network`` (source) connects, emits the batches as they arrive and ends when the server
  closes the stream, after ``idle_timeout_s`` without events, or on Ctrl-C (``Context.stop``).
  Before dv-processing connects, a plain socket checks within ``connect_timeout_s`` that the
  server is there and sends a DV stream header: dv-processing's reader holds Python's GIL
  while it waits for that header, so a wrong address could otherwise freeze the process beyond
  the reach of Ctrl-C.
* ``dv_network_server`` (sink) serves the chain's events to any number of clients (DV's GUI,
  dv-processing readers, another ``evchain run``). Its ``NetworkWriter`` lives in a process of
  its own (:mod:`evchain_dv.serve`), because dv-processing 2.0.4 deadlocks when a
  ``NetworkWriter`` is destroyed while a client is connected. At the end of the stream it
  lingers while clients are connected (``linger_s``): dv-processing's reader drops whatever it
  has not read yet once the server closes the connection.

The source polls: dv-processing's reader does not block (``getNextEventBatch`` returns
``None`` when nothing has arrived), so it waits between polls, from nothing while events flow
up to 0.25 ms when idle.
"""

from __future__ import annotations

import json
import queue
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, Geometry
from evchain.errors import ConfigError, DataError
from evchain.io.slicing import slice_stream
from pydantic import Field

from evchain_dv.aedat4 import _dv, dv_message, event_columns
from evchain_dv.serve import COMMAND, TIMEOUT

HEADER_ID = b"IOHE"  # flatbuffers identifier of the stream header, after its size and offset
HEADER_ID_AT = 8
MAX_WAIT_S = 2.5e-4  # longest pause between two polls of an idle stream: latency
RETRY_S = 0.05  # pause between connection attempts while the server is not up
START_TIMEOUT_S = 60.0  # the server process: start Python, import dv-processing, listen
SETTLE_S = 0.25  # a client counts once connected this long (connection checks come and go)


class Poll:
    """Pauses between polls of a stream that does not block: none while data flows, then
    doubling from 20 µs up to ``MAX_WAIT_S``."""

    def __init__(self):
        self.wait_s = 0.0

    def data(self) -> None:
        self.wait_s = 0.0

    def idle(self) -> None:
        self.wait_s = min(MAX_WAIT_S, max(2e-5, 2 * self.wait_s))
        time.sleep(self.wait_s)


def _recv_exactly(sock: socket.socket, n: int, deadline: float) -> bytes:
    data = b""
    while len(data) < n:
        sock.settimeout(max(deadline - time.monotonic(), 1e-3))
        try:
            chunk = sock.recv(n - len(data))
        except OSError:  # timed out, reset
            break
        if not chunk:
            break
        data += chunk
    return data


def open_stream(host: str, port: int, timeout_s: float, stop: threading.Event):
    """A dv-processing ``NetworkReader`` on ``host:port``, once a plain socket has seen the
    server's DV stream header; retries until ``timeout_s`` while the server is not up."""
    dv = _dv()
    where = f"{host}:{port}"
    deadline = time.monotonic() + timeout_s
    why = "nothing listening"
    while True:
        if stop.is_set():
            raise DataError(f"{where}: stopped (Ctrl-C) before the stream was connected")
        left = deadline - time.monotonic()
        if left <= 0:
            raise DataError(f"{where}: no DV event stream within {timeout_s:g} s ({why}); is "
                            "the server running, and are host and port right?")
        try:
            probe = socket.create_connection((host, port), timeout=min(left, 1.0))
        except socket.gaierror as exc:
            raise DataError(f"{where}: unknown host: {exc.strerror}") from None
        except OSError as exc:  # refused (not up yet), unreachable, timed out
            why = exc.strerror or type(exc).__name__
            time.sleep(min(RETRY_S, max(left, 0)))
            continue
        with probe:
            address = probe.getpeername()[0]
            head = _recv_exactly(probe, HEADER_ID_AT + len(HEADER_ID), deadline)
        if head[HEADER_ID_AT:] != HEADER_ID:
            got = f"got {head!r}" if head else f"received nothing within {timeout_s:g} s"
            raise DataError(f"{where}: not a DV (AEDAT 4) network stream: expected a stream "
                            f"header ({HEADER_ID.decode()!r} at byte {HEADER_ID_AT}), {got}")
        try:
            return dv.io.NetworkReader(address, port)
        except RuntimeError as exc:
            raise DataError(f"{where}: cannot read the DV stream: {dv_message(exc)}") from None


class DvNetworkSource(Filter):
    """Receive a live DV event stream (AEDAT 4 over TCP) with dv-processing."""

    name = "dv_network"
    produces = EventPacket
    ends_on_stop = True  # on Ctrl-C it hands over the events it holds, then ends

    class Params(FilterParams):
        host: str = Field("127.0.0.1", description="address of the server: DV's network "
                          "output, a dv-processing NetworkWriter or a dv_network_server")
        port: int = Field(ge=1, le=65535, description="TCP port of the server")
        packet_us: int | None = Field(None, ge=1, description="slice duration of each packet; "
                                      "None: one packet per batch as the stream delivers it "
                                      "(lowest latency; the events at a batch's last "
                                      "microsecond come with the next batch)")
        connect_timeout_s: float = Field(10.0, gt=0, description="how long to keep trying to "
                                         "connect (the server may start later)")
        idle_timeout_s: float | None = Field(None, gt=0, description="end the stream after "
                                             "this long without events; None: only when the "
                                             "server closes it, or on Ctrl-C")
        width: int | None = Field(None, ge=1, description="sensor width if the stream lacks it")
        height: int | None = Field(None, ge=1, description="sensor height if the stream lacks "
                                   "it")

    def setup(self, params, context):
        self.where = f"{params.host}:{params.port}"
        self.reader = open_stream(params.host, params.port, params.connect_timeout_s,
                                  context.stop)
        if not self.reader.isEventStreamAvailable():
            kind = self.reader.getStreamDefinition().mTypeIdentifier
            self.reader = None
            raise DataError(f"{self.where}: the stream carries {kind!r} data, not events "
                            "('EVTS'); connect to the server's event output")
        res = self.reader.getEventResolution()
        width = params.width or (res[0] if res else None)
        height = params.height or (res[1] if res else None)
        if width is None or height is None:
            raise DataError(f"{self.where}: the stream has no resolution; give the parameters "
                            "width and height")
        context.geometry = Geometry(int(width), int(height))
        super().setup(params, context)

    def packets(self) -> Iterator[EventPacket]:
        g = self.context.geometry
        if self.params.packet_us is not None:
            yield from slice_stream(self._columns(), g, self.params.packet_us)
            return
        # as delivered: a packet per batch, ending at its last event's time; the events of that
        # microsecond wait for the next batch (more may come at that very time)
        held, t0, done, last = None, None, 0, None
        for a in self._batches():
            cols = event_columns(a, g, self.where, done, last, before=held)
            done, last = done + len(a), int(cols["t"][-1])
            t0 = int(cols["t"][0]) if t0 is None else t0
            if last > t0:
                k = int(np.searchsorted(cols["t"], last))
                yield EventPacket(geometry=g, t_start=t0, t_end=last,
                                  **{c: v[:k] for c, v in cols.items()})
                held, t0 = {c: v[k:] for c, v in cols.items()}, last
            else:
                held = cols
        if held is not None and len(held["t"]):
            yield EventPacket(geometry=g, t_start=t0, t_end=last + 1, **held)

    def _columns(self) -> Iterator[dict[str, np.ndarray]]:
        done, last = 0, None
        for a in self._batches():
            yield event_columns(a, self.context.geometry, self.where, done, last)
            done, last = done + len(a), int(a["timestamp"][-1])

    def _batches(self) -> Iterator[np.ndarray]:
        """dv-processing's event array of every non-empty batch, until the stream ends."""
        reader, stop, idle_s = self.reader, self.context.stop, self.params.idle_timeout_s
        poll = Poll()
        done = 0
        last_data = time.monotonic()
        ended = False
        while not stop.is_set():
            try:
                batch = reader.getNextEventBatch()
            except RuntimeError as exc:
                raise DataError(f"{self.where}: after event {done}: cannot decode the next "
                                f"packet: {dv_message(exc)}") from None
            if batch is None or not len(batch):
                if ended:
                    return  # closed, and every batch that came before is read
                ended = not reader.isRunning()  # one more read: what came before the close
                if idle_s is not None and time.monotonic() - last_data > idle_s:
                    return
                if not ended:
                    poll.idle()
                continue
            poll.data()
            last_data = time.monotonic()
            done += len(batch)
            yield batch.numpy()

    def close(self):
        self.reader = None


class ServerProcess:
    """The process of :mod:`evchain_dv.serve`, serving one event stream on ``host:port``."""

    def __init__(self, host: str, port: int, geometry: Geometry, camera: str):
        self.where = f"{host}:{port}"
        script = Path(__file__).with_name("serve.py")
        self.proc = subprocess.Popen(
            [sys.executable, str(script), host, str(port), str(geometry.width),
             str(geometry.height), camera], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.answers: queue.Queue = queue.Queue()
        threading.Thread(target=self._read_answers, daemon=True).start()
        first = self._answer(START_TIMEOUT_S, "starting")
        if "error" in first:
            self.kill()
            raise ConfigError(f"dv_network_server: cannot serve on {self.where}: "
                              f"{dv_message(RuntimeError(first['error']))}")

    def _read_answers(self) -> None:
        for line in self.proc.stdout:
            self.answers.put(json.loads(line))
        self.answers.put(None)

    def _answer(self, timeout_s: float, doing: str) -> dict:
        try:
            got = self.answers.get(timeout=timeout_s)
        except queue.Empty:
            raise DataError(f"{self.where}: the server process did not answer within "
                            f"{timeout_s:g} s ({doing})") from None
        if got is None:
            raise DataError(f"{self.where}: the server process ended unexpectedly ({doing}; "
                            f"exit code {self.proc.wait()})")
        return got

    def _write(self, data: bytes, doing: str) -> None:
        try:
            self.proc.stdin.write(data)
            self.proc.stdin.flush()
        except OSError:
            raise DataError(f"{self.where}: the server process ended unexpectedly ({doing}; "
                            f"exit code {self.proc.wait()})") from None

    def send(self, packet: EventPacket) -> None:
        """Hand the packet's events over; the server sends them as one packet."""
        n = len(packet)
        cols = [packet.t.astype("<i8", copy=False), packet.x.astype("<u2", copy=False),
                packet.y.astype("<u2", copy=False), packet.p.astype("i1", copy=False)]
        self._write(b"".join([COMMAND.pack(b"E", n), *(c.tobytes() for c in cols)]),
                    "sending events")

    def clients(self) -> int:
        self._write(COMMAND.pack(b"C", 0), "counting clients")
        return int(self._answer(START_TIMEOUT_S, "counting clients")["clients"])

    def drain(self, timeout_s: float) -> int:
        """Wait until every packet has left (at most ``timeout_s``); returns the number of
        packets not sent."""
        self._write(COMMAND.pack(b"D", 0) + TIMEOUT.pack(timeout_s), "sending the last packets")
        return int(self._answer(timeout_s + START_TIMEOUT_S, "sending the last packets")
                   ["queued"])

    def end(self) -> None:
        """End the server process: its clients see the end of the stream."""
        self._write(COMMAND.pack(b"X", 0), "ending the stream")
        self.kill()  # it is ending: collect it

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=START_TIMEOUT_S)
        self.proc.stdin.close()


class DvNetworkServer(Filter):
    """Serve the events passing through as a live DV event stream (AEDAT 4 over TCP)."""

    name = "dv_network_server"
    consumes = EventPacket

    class Params(FilterParams):
        host: str = Field("127.0.0.1", description="address to listen on (0.0.0.0: every "
                          "network interface)")
        port: int = Field(ge=1, le=65535, description="TCP port to listen on")
        camera: str = Field("evchain", description="camera name announced in the stream")
        wait_for_clients: int = Field(0, ge=0, description="before the first events are sent, "
                                      "wait until this many clients are connected, so that a "
                                      "viewer started after evchain sees the whole stream")
        timeout_s: float = Field(30.0, gt=0, description="longest wait for those clients, and "
                                 "at the end for the last packets to leave")
        linger_s: float = Field(1.0, ge=0, description="after the last packet has left, keep "
                                "the stream open until every client has disconnected, at most "
                                "this long: dv-processing's reader drops what it has not read "
                                "yet when the server closes the stream")

    def setup(self, params, context):
        self.server: ServerProcess | None = None
        self.geometry: Geometry | None = None
        super().setup(params, context)
        if context.geometry is not None:  # listen now: clients can connect before the stream
            self._start(context.geometry)

    def reset(self):
        self.waited = False

    def _start(self, geometry: Geometry) -> None:
        p = self.params
        self.server = ServerProcess(p.host, p.port, geometry, p.camera)
        self.geometry = geometry

    def process(self, packet: EventPacket) -> EventPacket:
        if self.server is None:
            self._start(packet.geometry)
        elif packet.geometry.shape != self.geometry.shape:
            raise DataError(f"{self.server.where}: packet at {packet.t_start} us is "
                            f"{packet.geometry.width}x{packet.geometry.height}, the stream is "
                            f"{self.geometry.width}x{self.geometry.height}")
        if not self.waited:
            self._wait_for_clients()
            self.waited = True
        if len(packet):
            self.server.send(packet)
        return packet

    def _wait_for_clients(self) -> None:
        """Until ``wait_for_clients`` clients have stayed connected ``SETTLE_S`` (a connection
        check that comes and goes does not count), at most ``timeout_s``; Ctrl-C ends it."""
        want, stop = self.params.wait_for_clients, self.context.stop
        if not want:
            return
        deadline = time.monotonic() + self.params.timeout_s
        since = None
        while not stop.is_set():
            now = time.monotonic()
            if self.server.clients() >= want:
                since = now if since is None else since
                if now - since >= SETTLE_S:
                    return
            else:
                since = None
            if now > deadline:
                raise DataError(f"{self.server.where}: {want} client(s) expected, not connected "
                                f"within {self.params.timeout_s:g} s (wait_for_clients)")
            time.sleep(0.01)

    def flush(self):
        """Send what is queued, linger while clients are connected (``linger_s``; Ctrl-C ends
        it), then end the stream."""
        server, p = self.server, self.params
        if server is None:
            return None
        left = server.drain(p.timeout_s)
        deadline = time.monotonic() + p.linger_s
        while (time.monotonic() < deadline and not self.context.stop.is_set()
               and server.clients()):
            time.sleep(0.01)
        server.end()
        self.server = None
        if left:
            self.context.warn(f"dv_network_server {p.host}:{p.port}: {left} packet(s) not sent "
                              f"within {p.timeout_s:g} s at the end of the stream")
        return None

    def close(self):
        if getattr(self, "server", None) is not None:  # no flush: the run failed; stop now
            self.server.kill()
            self.server = None
