"""Streaming packets through a list of stages: in order on the calling thread, or with every
stage on a thread of its own.

A stage is anything with ``process(packet) -> packet`` and ``flush() -> packet | None`` (a
:class:`~evchain.core.filter.Filter`, or the chain's timed wrapper of one). Both ways give the
same packets in the same order: each source packet through every stage, then, once the stream
has passed every stage, each stage's flush output through the stages after it. Each stage sees
the same packets in the same order either way, so its results are the same bit for bit; with
threads, stage i works on packet k + 1 while stage i + 1 works on packet k, and the kernels
that release the GIL (numba's ``nogil``) run at the same time on several cores.

With :class:`StageThreads` every call of a stage runs on that stage's thread (set-up and
close too, through :meth:`StageThreads.call`): resources that must stay on the thread that
made them (an SQLite connection, say) work as without threads. The threads are joined by
bounded queues (:data:`DEPTH` packets each), so memory stays bounded. An exception in any
stage ends the stream and is raised in the consuming thread; the packets still in flight are
dropped, and no stage is flushed.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, Protocol

#: packets waiting between two stages
DEPTH = 4
_POLL_S = 0.1
_END = object()       # the stream ended; passed on
_FLUSH = object()     # flush now: put in a stage's inbox by the consumer
_FLUSHED = object()   # a stage's flush output (if any) came before this; passed on
_QUIT = object()      # the thread ends


class Stage(Protocol):
    def process(self, packet: Any) -> Any: ...

    def flush(self) -> Any | None: ...


def in_order(source: Iterable[Any], stages: Sequence[Stage]) -> Iterator[Any]:
    """The last stage's packets, every stage called on the calling thread."""
    for packet in source:
        for s in stages:
            packet = s.process(packet)
        yield packet
    for i, s in enumerate(stages):
        packet = s.flush()
        if packet is not None:
            for later in stages[i + 1:]:
                packet = later.process(packet)
            yield packet


def in_threads(source: Iterable[Any], stages: Sequence[Stage]) -> Iterator[Any]:
    """The same packets as :func:`in_order`; the source is iterated on a thread of its own
    and each stage runs on one of its own."""
    with StageThreads(len(stages) + 1) as threads:
        yield from threads.stream(lambda: source, stages)


class _Failed:
    """An exception raised on a stage's thread, on its way to the consumer."""

    def __init__(self, exc: BaseException):
        self.exc = exc


class _Call:
    """A function to run on a stage's thread, and its outcome."""

    def __init__(self, fn: Callable, args: tuple):
        self.fn, self.args = fn, args
        self.done = threading.Event()
        self.result: Any = None
        self.exc: BaseException | None = None

    def run(self) -> None:
        try:
            self.result = self.fn(*self.args)
        except BaseException as exc:  # handed to the caller
            self.exc = exc
        self.done.set()


class StageThreads:
    """``n`` threads, thread 0 for the source and thread i for stage i, each running the calls
    and packets put in its inbox in order. :meth:`close` (or leaving it as a context
    manager) ends them."""

    def __init__(self, n: int):
        self._inboxes = [queue.Queue(DEPTH) for _ in range(n)]
        self._out: queue.Queue = queue.Queue(DEPTH)
        self._abort = threading.Event()
        self._stages: Sequence[Stage] = ()
        self._threads = [threading.Thread(target=self._loop, args=(i,), daemon=True,
                                          name=f"evchain-stage-{i}") for i in range(n)]
        for t in self._threads:
            t.start()

    def __enter__(self) -> StageThreads:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End every thread (after the calls already put in its inbox)."""
        self._abort.set()
        for box in self._inboxes:
            box.put(_QUIT)
        for t in self._threads:
            t.join()

    def call(self, i: int, fn: Callable, *args) -> Any:
        """``fn(*args)`` on thread i, after what its inbox holds; its result, or its
        exception raised here."""
        c = _Call(fn, args)
        self._inboxes[i].put(c)
        while not c.done.wait(_POLL_S):
            pass
        if c.exc is not None:
            raise c.exc
        return c.result

    def stream(self, source: Callable[[], Iterable[Any]], stages: Sequence[Stage]
               ) -> Iterator[Any]:
        """The packets of :func:`in_order` (``source()`` iterated on thread 0, stage i - 1
        of ``stages`` on thread i). Ends every thread's part in the stream when the consumer
        stops early or a stage fails."""
        self._stages = stages
        n = len(stages)
        self._inboxes[0].put(_Call(self._feed, (source,)))
        finished = False
        try:
            yield from self._until(_END)
            for i in range(1, n + 1):  # every stage has passed the stream on: flush in order
                self._inboxes[i].put(_FLUSH)
                yield from self._until(_FLUSHED)
            finished = True
        finally:
            if not finished:
                self._abort.set()  # drop what is in flight; calls still run

    def _until(self, marker) -> Iterator[Any]:
        while True:
            try:
                item = self._out.get(timeout=_POLL_S)
            except queue.Empty:
                if not all(t.is_alive() for t in self._threads):
                    raise RuntimeError("a stage thread ended in the stream") from None
                continue
            if item is marker:
                return
            if isinstance(item, _Failed):
                raise item.exc
            yield item

    def _put(self, i: int, item) -> None:
        """Hand ``item`` on from thread i (to stage i + 1, or to the consumer)."""
        box = self._inboxes[i + 1] if i + 1 < len(self._inboxes) else self._out
        while not self._abort.is_set():
            try:
                box.put(item, timeout=_POLL_S)
                return
            except queue.Full:
                pass

    def _feed(self, source: Callable[[], Iterable[Any]]) -> None:
        try:
            for packet in source():
                self._put(0, packet)
                if self._abort.is_set():
                    return
            self._put(0, _END)
        except BaseException as exc:
            self._put(0, _Failed(exc))

    def _loop(self, i: int) -> None:
        failed = False
        while True:
            item = self._inboxes[i].get()
            if item is _QUIT:
                return
            if isinstance(item, _Call):
                item.run()
            elif self._abort.is_set() or failed:
                continue  # the stream was given up: drop what is in flight
            elif item is _END or item is _FLUSHED or isinstance(item, _Failed):
                self._put(i, item)
                failed = isinstance(item, _Failed)
            else:  # a packet, or _FLUSH: the stage's own flush
                stage, flushing = self._stages[i - 1], item is _FLUSH
                try:
                    out = stage.flush() if flushing else stage.process(item)
                except BaseException as exc:
                    failed = True
                    self._put(i, _Failed(exc))
                    continue
                if out is not None or not flushing:  # a flush may have nothing left
                    self._put(i, out)
                if flushing:
                    self._put(i, _FLUSHED)
