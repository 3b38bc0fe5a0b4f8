"""A plain dv-processing network server for the tests (run as a script, not collected):
``python dv_writer.py PORT EVENTS.npz BATCH``.

Listens on 127.0.0.1:PORT (a 346x260 event stream), prints ``listening``, waits for a line on
stdin, sends the events of EVENTS.npz (arrays t, x, y, p with p in {-1, +1}) in stores of
BATCH events and prints ``sent N`` once dv-processing's queue is empty. At the next line (or
the end of stdin) it ends, and the operating system closes the connections: clients see the
end of the stream. (It waits because dv-processing's reader drops what it has not read yet
when the server closes.)
"""

import os
import sys
import time

import dv_processing as dv
import numpy as np

port, path, batch = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
ev = np.load(path)
stream = dv.io.Stream.EventStream(0, "events", "test-writer", (346, 260))
writer = dv.io.NetworkWriter("127.0.0.1", port, stream, 10, lambda code, msg: None)
print("listening", flush=True)
sys.stdin.readline()
n = len(ev["t"])
for i in range(0, n, batch):
    store = dv.EventStore()
    for t, x, y, p in zip(ev["t"][i:i + batch].tolist(), ev["x"][i:i + batch].tolist(),
                          ev["y"][i:i + batch].tolist(), ev["p"][i:i + batch].tolist(),
                          strict=True):
        store.push_back(t, x, y, p > 0)
    writer.writeEvents(store)
deadline = time.monotonic() + 30
while writer.getQueuedPacketCount() and time.monotonic() < deadline:
    time.sleep(0.001)
print(f"sent {n}", flush=True)
sys.stdin.readline()
os._exit(0)
