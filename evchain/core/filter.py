"""The filter contract: one small class per stage, parameters as a nested pydantic model.

Life cycle, driven by the chain::

    f = FilterClass()
    f.setup(params, context)      # once; the base stores both and calls reset()
    for packet in stream:         # sources: for packet in f.packets()
        out = f.process(packet)   # one packet in, one packet out, same time slice
    last = f.flush()              # end of stream: a final packet (or None), metrics into context
    f.close()                     # always, on success and on error: release resources

``reset()`` clears all state so that replaying the stream gives the same output. Filters keep
explicit state arrays, never display or file code unless they are sinks; timing and counters
are the chain's job. Numba kernels live in ``evchain.kernels`` and are imported lazily.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from evchain.core import truth as _truth
from evchain.core.packets import Geometry, Packet
from evchain.core.renderer import FrameRenderer
from evchain.core.series import SeriesDef
from evchain.core.truth import Truth


class FilterParams(BaseModel):
    """Base for every filter's ``Params``: unknown keys are errors, numbers are finite (``.inf``
    and ``.nan`` are errors), values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


@dataclass
class Context:
    """What the filters of one run share.

    ``geometry``, ``truth`` and ``renderer`` are set by the source during its ``setup``:
    ``truth`` is the ground-truth provider (protocols in :mod:`evchain.core.truth`), read by
    scorers, picture sinks and oracles (``exact_speed``) only; ``renderer`` renders the source's
    frames at any time, for picture sinks (:mod:`evchain.core.renderer`). ``metrics`` is filled
    by scorers (it becomes ``report.json``'s ``metrics``); ``out_dir`` is where sinks write;
    ``warnings`` (:meth:`warn`) become ``report.json``'s ``warnings``. ``stop`` is set when the
    user asks the run to stop (the first Ctrl-C): the chain ends the stream after the packet in
    flight and flushes every filter; a source that waits for data (a live stream) checks it
    while it waits and returns.
    """

    seed: int = 0
    out_dir: Path = field(default_factory=lambda: Path("."))
    geometry: Geometry | None = None
    truth: Truth | None = None
    renderer: FrameRenderer | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    debug: bool = False
    warnings: list[str] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)

    def warn(self, message: str) -> None:
        """Something the run accepted but the user should know (in ``report.json`` and on the
        ``evchain`` logger)."""
        import logging

        self.warnings.append(message)
        logging.getLogger("evchain").warning("warning: %s", message)

    def rng(self, stream: str) -> np.random.Generator:
        """A generator for ``stream`` (e.g. the filter's id), fixed by the run's seed.

        Independent of the order in which filters ask and of Python's hash seed.
        """
        key = int.from_bytes(hashlib.sha256(stream.encode()).digest()[:8], "little")
        return np.random.default_rng([self.seed, key])

    def output_path(self, path: str | Path) -> Path:
        """``path`` resolved against the output folder (absolute paths are kept)."""
        p = Path(path)
        return p if p.is_absolute() else self.out_dir / p


class Filter:
    """Base class of every stage. Subclasses set ``name``, ``consumes``, ``produces`` and
    ``Params``, allocate their state in :meth:`reset` and implement :meth:`process` (or
    :meth:`packets` for sources, which consume ``None``).

    Series (:mod:`evchain.core.series`) are declared beside the packet types:
    ``needs_series`` must be added by an earlier stage (validation rejects the chain
    otherwise), ``optional_series`` are read when an earlier stage adds them, ``adds_series``
    are attached to the output packets (:meth:`series_added` when a parameter names them).

    Files: ``input_paths`` names the parameters that are files (or folders) the stage reads;
    validation makes them absolute (relative to the pipeline file's folder, or to the current
    folder for ``--set``) and checks that they exist. ``output_paths`` names the parameters
    that are files (or folders) the stage writes in the run folder: they must stay inside it,
    and a run removes them before it starts, so that no earlier run's file looks current.
    """

    name: ClassVar[str] = ""
    consumes: ClassVar[type[Packet] | None] = None
    produces: ClassVar[type[Packet] | None] = None
    needs_series: ClassVar[tuple[SeriesDef, ...]] = ()
    optional_series: ClassVar[tuple[SeriesDef, ...]] = ()
    adds_series: ClassVar[tuple[SeriesDef, ...]] = ()
    input_paths: ClassVar[tuple[str, ...]] = ()
    output_paths: ClassVar[tuple[str, ...]] = ()
    Params: ClassVar[type[FilterParams]] = FilterParams
    #: ground truth (protocols of :mod:`evchain.core.truth`) this stage cannot work without;
    #: :meth:`setup` checks it and stores the truth as ``self.truth``
    needs_truth: ClassVar[tuple[type, ...]] = ()
    #: ground truth this stage uses when the truth has it (it says what it could not score)
    uses_truth: ClassVar[tuple[type, ...]] = ()
    #: another way to give this stage its truth, named when the truth is missing
    truth_hint: ClassVar[str] = ""
    #: the ground truth a source (or a stage, for the stages after it) sets as ``context.truth``
    provides_truth: ClassVar[tuple[type, ...]] = ()
    #: sources: it watches ``context.stop`` (Ctrl-C) and then ends its stream itself, with the
    #: packets it still holds (a live stream); other sources get no further turn once it is set
    ends_on_stop: ClassVar[bool] = False
    #: the stage that turns the scene into sensor data (emulator, aps): the report's CPU time
    #: per simulated second counts the stages after the last sensor (or after the source)
    sensor: ClassVar[bool] = False
    #: scores against the ground truth (flow_scorer, foe_ttc_scorer): measurement, not part of
    #: the chain, so left out of the report's CPU time per simulated second
    scorer: ClassVar[bool] = False

    params: Any
    context: Context
    id: str

    def setup(self, params: FilterParams, context: Context) -> None:
        """Store parameters and context, check the sensor size (:meth:`check_sensor`, if the
        source has set ``context.geometry``) and the ground truth that ``needs_truth`` asks
        for (a ConfigError naming the stage without it), then :meth:`reset`. Override to open
        files etc."""
        self.params = params
        self.context = context
        if not hasattr(self, "id"):
            self.id = self.name
        g = context.geometry
        problem = None if g is None else self.check_sensor(params, g.width, g.height)
        if problem:
            from evchain.errors import ConfigError

            raise ConfigError(f"{problem} (the source's sensor is {g.width}x{g.height})",
                              key=self.id)
        if self.needs_truth or self.uses_truth:
            self.truth = self.truth_for(params, context)
            stage = repr(self.id) if self.id == self.name else f"{self.id!r} ({self.name})"
            _truth.require(stage, self.needs_truth, self.truth, self.truth_hint)
        self.reset()

    def truth_for(self, params: FilterParams, context: Context) -> Truth | None:
        """The ground truth this stage reads (if it declares ``needs_truth`` or
        ``uses_truth``): the source's ``context.truth``; a stage may take it from elsewhere
        (e.g. a file named in its parameters)."""
        return context.truth

    def reset(self) -> None:
        """Clear all state (a replay after reset gives the same output)."""

    def process(self, packet: Packet) -> Packet:
        """Turn one packet into the next; sinks pass it on unchanged."""
        raise TypeError(f"filter {self.name!r} is a source: it has packets(), not process()")

    def packets(self) -> Iterator[Packet]:
        """Sources only: yield packets of consecutive slices."""
        raise TypeError(f"filter {self.name!r} is not a source: it has process(), not packets()")

    def time_span_us(self) -> tuple[int, int] | None:
        """Sources: the stream's first and last time if known (drives the progress bar)."""
        return None

    def flush(self) -> Packet | None:
        """End of stream: return what is still held back (or None); scorers write metrics."""
        return None

    def close(self) -> None:
        """Release resources; runs on success and on error (after flush on success)."""

    @classmethod
    def output_files(cls, params: FilterParams) -> list[str]:
        """The files and folders (relative to the run folder) a stage with ``params`` writes:
        the values of its ``output_paths``. A run removes them before it starts."""
        return [v for v in (getattr(params, k) for k in cls.output_paths) if v is not None]

    @classmethod
    def series_added(cls, params: FilterParams) -> tuple[SeriesDef, ...]:
        """The series a stage with ``params`` adds: ``adds_series`` unless a parameter renames
        them."""
        return cls.adds_series

    @classmethod
    def sensor_size(cls, params: FilterParams) -> tuple[int, int] | None:
        """Sources: the sensor's (width, height) when the parameters fix it before anything
        runs: the parameters ``width`` and ``height`` of a source that always has both (plain
        ints). None for other stages and for sources whose size comes from their input
        (optional ``width``/``height`` only fill in what a file lacks)."""
        fields = type(params).model_fields
        if not cls.is_source() or any(k not in fields or fields[k].annotation is not int
                                      for k in ("width", "height")):
            return None
        return params.width, params.height

    @classmethod
    def check_sensor(cls, params: FilterParams, width: int, height: int) -> str | None:
        """What is wrong with a stage with ``params`` on a ``width`` x ``height`` sensor (a
        sentence naming the limit and what to use instead), or None if nothing is. Checked
        when a pipeline is loaded (if the source's parameters fix the size) and again at
        setup (from ``context.geometry``), before any packet flows."""
        return None

    def metrics_key(self, group: str) -> str:
        """Where this stage writes its ``group`` of metrics in ``context.metrics``: ``group``,
        or ``group@ID`` when the stage has an ``id`` of its own (two scorers of one kind)."""
        return group if self.id == self.name else f"{group}@{self.id}"

    @classmethod
    def summary(cls) -> str:
        """First line of the docstring: the one-line description in ``evchain filters``."""
        return (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""

    @classmethod
    def is_source(cls) -> bool:
        return cls.consumes is None
