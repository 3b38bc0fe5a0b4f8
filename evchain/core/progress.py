"""A run's progress bar: simulated seconds of the source's time span, and a notice while numba
compiles kernels.

The first run on a machine compiles the numba kernels (later runs load them from numba's
cache); that takes a while in the first packet and would otherwise show as a stuck bar with an
absurd remaining time. While a compilation runs, the bar says ``compiling kernels (first run
only)`` and the ``evchain`` logger says so once (at DEBUG level when no bar is shown); the
time spent compiling is left out of the bar's rate and remaining time.
"""

from __future__ import annotations

import logging
import sys
import threading
import time

from numba.core import event

log = logging.getLogger("evchain")

COMPILING = "compiling kernels (first run only)"
_announced = False


class RunProgress:
    """Progress over ``span`` (µs, or None when unknown) shown as simulated seconds; ``bar``
    False shows none (compilation is still announced on the logger)."""

    def __init__(self, label: str, span: tuple[int, int] | None, bar: bool):
        self.label = label
        self.t0 = span[0] if span else 0
        self.bar = None
        if bar:
            from tqdm import tqdm

            seconds = "{n:.2f}/{total:.2f} s simulated" if span else "{n:.2f} s simulated"
            remaining = "<{remaining}" if span else ""
            self.bar = tqdm(
                total=(span[1] - span[0]) / 1e6 if span else None, unit="s", desc=label,
                leave=False, file=sys.stderr, dynamic_ncols=True, mininterval=0.5,
                disable=None, bar_format="{desc}: " + ("{percentage:3.0f}%|{bar}| " if span
                                                       else "") +
                seconds + " [{elapsed}" + remaining + ", {rate_noinv_fmt}]")
            if self.bar.disable:  # not a terminal (disable=None): no bar to move or annotate
                self.bar = None
        self._lock = threading.Lock()
        self._depth = 0
        self._started = 0.0
        self._listener = _CompileListener(self)
        event.register("numba:compile", self._listener)

    def update(self, t_us: int) -> None:
        """The stream has reached ``t_us``."""
        if self.bar is not None:
            done = (t_us - self.t0) / 1e6
            if done > self.bar.n:
                self.bar.update(done - self.bar.n)

    def close(self) -> None:
        event.unregister("numba:compile", self._listener)
        if self.bar is not None:
            self.bar.close()

    # -- called by the numba listener, possibly from a render thread -----------------------
    def compile_started(self) -> None:
        global _announced
        with self._lock:
            self._depth += 1
            if self._depth > 1:
                return
            self._started = time.perf_counter()
        if not _announced:
            _announced = True
            if self.bar is not None:
                self.bar.clear()  # the notice on a line of its own, not after the bar
            # without a bar (sweep workers, --no-progress) only with --debug: a sweep's
            # workers would each print it over the sweep's own lines
            log.log(logging.INFO if self.bar is not None else logging.DEBUG,
                    "%s: numba compiles the kernels once; later runs load them from its cache",
                    COMPILING)
        if self.bar is not None:
            self.bar.set_description_str(COMPILING)

    def compile_ended(self) -> None:
        with self._lock:
            self._depth -= 1
            if self._depth > 0:
                return
            spent = time.perf_counter() - self._started
        if self.bar is not None:  # compile time counts towards neither rate nor remaining time
            self.bar.start_t += spent
            self.bar.last_print_t += spent
            self.bar.set_description_str(self.label)


class _CompileListener(event.Listener):
    """Tells a :class:`RunProgress` when numba starts and ends compiling."""

    def __init__(self, progress: RunProgress):
        self.progress = progress

    def on_start(self, ev) -> None:
        self.progress.compile_started()

    def on_end(self, ev) -> None:
        self.progress.compile_ended()
