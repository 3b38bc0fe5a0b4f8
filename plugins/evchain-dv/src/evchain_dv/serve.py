"""The process that hosts dv-processing's ``NetworkWriter`` for the ``dv_network_server`` sink.

Run as a script (``python serve.py HOST PORT WIDTH HEIGHT CAMERA``) by
:class:`evchain_dv.network.ServerProcess`; it imports only numpy and dv-processing.

Why a process of its own: in dv-processing 2.0.4, destroying a ``NetworkWriter`` while a client
is connected deadlocks (the writer's network thread reports the closed connection through a
callback that takes Python's GIL, while the destructor holds the GIL and waits for that
thread). This process never destroys its writer: once the last packet has left, it ends with
``os._exit`` and the operating system closes the connections, which clients see as the end of
the stream. Ctrl-C is ignored here: it is the sink's to handle (it ends the stream).

Commands on stdin, each a header ``<cQ`` (kind, count) and a payload:

* ``E`` n: n events, as the columns ``t`` int64, ``x`` uint16, ``y`` uint16, ``p`` int8 (+1/-1),
  one after the other, little endian; they are sent as one event packet;
* ``C`` 0: answer ``{"clients": N}``, the number of connected clients;
* ``D`` 0 and a float64 timeout in seconds: wait until every packet has left (at most the
  timeout), answer ``{"queued": N}`` (packets not sent);
* ``X`` 0: end the process, and with it the stream.

Answers are JSON lines on the original stdout (anything else printed goes to stderr); the first
is ``{"ready": true}`` or ``{"error": MESSAGE}`` when the server cannot listen. End of input
(the sink is gone) ends the process.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import sys
import time
from collections import deque

COMMAND = struct.Struct("<cQ")
EVENT_BYTES = 8 + 2 + 2 + 1  # t, x, y, p
TIMEOUT = struct.Struct("<d")


def _answer(out, **fields) -> None:
    out.write(json.dumps(fields) + "\n")
    out.flush()


def _ignore(code, message) -> None:
    """Client errors (a viewer that went away) are not this stream's end."""


def main(argv: list[str]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    out = os.fdopen(os.dup(1), "w")  # answers; stray prints of the library go to stderr
    os.dup2(2, 1)
    host, port, width, height, camera = argv
    import dv_processing as dv
    import numpy as np

    try:
        stream = dv.io.Stream.EventStream(0, "events", camera, (int(width), int(height)))
        writer = dv.io.NetworkWriter(host, int(port), stream, 10, _ignore)
    except RuntimeError as exc:
        _answer(out, error=str(exc))
        os._exit(0)
    _answer(out, ready=True)
    inp = sys.stdin.buffer
    while True:
        head = inp.read(COMMAND.size)
        if len(head) < COMMAND.size:
            os._exit(0)  # the sink is gone
        kind, n = COMMAND.unpack(head)
        if kind == b"E":
            body = inp.read(n * EVENT_BYTES)
            if len(body) < n * EVENT_BYTES:
                os._exit(0)
            t = np.frombuffer(body, "<i8", n, 0)
            x = np.frombuffer(body, "<u2", n, 8 * n)
            y = np.frombuffer(body, "<u2", n, 10 * n)
            p = np.frombuffer(body, "i1", n, 12 * n)
            store = dv.EventStore()
            # no numpy path into an EventStore: one push_back per event, driven by map()
            deque(map(store.push_back, zip(t.tolist(), x.tolist(), y.tolist(),
                                           (p > 0).tolist(), strict=True)), maxlen=0)
            writer.writeEvents(store)
        elif kind == b"C":
            _answer(out, clients=writer.getClientCount())
        elif kind == b"D":
            (timeout_s,) = TIMEOUT.unpack(inp.read(TIMEOUT.size))
            deadline = time.monotonic() + timeout_s
            while writer.getQueuedPacketCount() and time.monotonic() < deadline:
                time.sleep(0.001)
            _answer(out, queued=writer.getQueuedPacketCount())
        elif kind == b"X":
            os._exit(0)
        else:
            _answer(out, error=f"unknown command {kind!r}")
            os._exit(1)


if __name__ == "__main__":
    main(sys.argv[1:])
