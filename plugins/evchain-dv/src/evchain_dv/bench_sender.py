"""The sending end of the network benchmarks (:mod:`evchain_dv.bench_network`), a process of its
own: ``python bench_sender.py KIND PORT EVENTS.npz BATCH PERIOD_S``.

KIND is what sends the events of EVENTS.npz (arrays t, x, y, p) on 127.0.0.1:PORT, in batches
of BATCH events:

* ``plain``: dv-processing as a Python program uses it: an ``EventStore`` filled with
  ``push_back`` per batch, then ``NetworkWriter.writeEvents``;
* ``prebuilt``: the stores are filled before the start, so only ``writeEvents`` runs, as in a
  program that has its events in dv-processing's stores already (a camera driver, DV);
* ``evchain``: evchain packets through the ``dv_network_server`` sink.

With PERIOD_S > 0 a batch leaves, then the sender pauses PERIOD_S seconds, and so on; each
batch's events are stamped with the time it starts on its way (``time.monotonic_ns`` in µs,
one µs apart and ending at that time, before the store is filled or the packet made): the
receiver's clock minus an event's time is its latency. Otherwise the batches leave as fast as
they can, with the file's times.

Prints ``ready`` once listening (and, for ``prebuilt``, the stores are filled), starts at a
line on stdin, prints ``sent N`` once every packet has left (``evchain``: once the receiver has
disconnected), and ends at the next line.
"""

from __future__ import annotations

import os
import sys
import time
from collections import deque


def stamped(n: int):
    """``n`` times one µs apart ending now (µs of the monotonic clock)."""
    import numpy as np

    now = time.monotonic_ns() // 1000
    return np.arange(now - n + 1, now + 1, dtype=np.int64)


def main(kind: str, port: int, path: str, batch: int, period_s: float) -> None:
    import dv_processing as dv
    import numpy as np

    ev = np.load(path)
    n = len(ev["t"])
    cuts = range(0, n, batch)
    cols = {c: ev[c] for c in ("t", "x", "y", "p")}
    if kind == "evchain":
        from evchain.core.filter import Context
        from evchain.core.packets import EventPacket, Geometry

        from evchain_dv.network import DvNetworkServer

        g = Geometry(346, 260)
        sink = DvNetworkServer()
        sink.id = sink.name
        sink.setup(DvNetworkServer.Params(port=port, timeout_s=600, linger_s=600),
                   Context(geometry=g))
        t_end = None

        def send(i: int, t) -> None:
            nonlocal t_end
            t_start = int(t[0]) if t_end is None else t_end
            t_end = int(t[-1]) + 1
            sink.process(EventPacket(geometry=g, t_start=t_start, t_end=t_end,
                                     x=cols["x"][i:i + len(t)], y=cols["y"][i:i + len(t)], t=t,
                                     p=cols["p"][i:i + len(t)]))
    else:
        stream = dv.io.Stream.EventStream(0, "events", "bench", (346, 260))
        writer = dv.io.NetworkWriter("127.0.0.1", port, stream, 10, lambda code, msg: None)

        def store(i: int, t) -> object:
            s = dv.EventStore()
            j = i + len(t)
            rows = zip(t.tolist(), cols["x"][i:j].tolist(), cols["y"][i:j].tolist(),
                       (cols["p"][i:j] > 0).tolist(), strict=True)
            deque(map(s.push_back, rows), maxlen=0)
            return s

        if kind == "prebuilt":
            stores = {i: store(i, cols["t"][i:i + batch]) for i in cuts}

            def send(i: int, t) -> None:
                writer.writeEvents(stores[i])
        else:
            def send(i: int, t) -> None:
                writer.writeEvents(store(i, t))
    print("ready", flush=True)
    sys.stdin.readline()
    for i in cuts:
        if period_s > 0:  # a pause after each batch: stamps of two batches never overlap
            send(i, stamped(min(batch, n - i)))
            time.sleep(period_s)
        else:
            send(i, cols["t"][i:i + batch])
    if kind == "evchain":
        sink.flush()
    else:
        deadline = time.monotonic() + 600
        while writer.getQueuedPacketCount() and time.monotonic() < deadline:
            time.sleep(0.001)
    print(f"sent {n}", flush=True)
    sys.stdin.readline()
    os._exit(0)  # never destroy a NetworkWriter: with a client connected that deadlocks


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), float(sys.argv[5]))
