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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict

from evchain.core.packets import Geometry, Packet
from evchain.core.series import SeriesDef


@runtime_checkable
class GroundTruth(Protocol):
    """What a source knows exactly. Times ``t_us`` are µs (scalars or arrays, float allowed).

    Providers implement what they can (``flow``, ``foe``, ``ttc``, ``depth``; a simulator also
    ``object_id(x, y, t_us)`` and ``obstacle_ids``: which object is seen where); a method they
    cannot answer simply does not exist, and scorers check with ``hasattr``. Undefined values
    are NaN (e.g. the FOE when not moving forward).
    """

    def flow(self, x: np.ndarray, y: np.ndarray, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Motion field (vx, vy) in px/s at pixel positions and times."""
        ...


class FilterParams(BaseModel):
    """Base for every filter's ``Params``: unknown keys are errors; values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass
class Context:
    """What the filters of one run share.

    ``geometry`` and ``truth`` are set by the source during its ``setup``; ``metrics`` is filled
    by scorers (it becomes ``report.json``'s ``metrics``); ``out_dir`` is where sinks write.
    """

    seed: int = 0
    out_dir: Path = field(default_factory=lambda: Path("."))
    geometry: Geometry | None = None
    truth: Any = None
    metrics: dict[str, Any] = field(default_factory=dict)
    debug: bool = False

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
    """

    name: ClassVar[str] = ""
    consumes: ClassVar[type[Packet] | None] = None
    produces: ClassVar[type[Packet] | None] = None
    needs_series: ClassVar[tuple[SeriesDef, ...]] = ()
    optional_series: ClassVar[tuple[SeriesDef, ...]] = ()
    adds_series: ClassVar[tuple[SeriesDef, ...]] = ()
    Params: ClassVar[type[FilterParams]] = FilterParams
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
        """Store parameters and context, then :meth:`reset`. Override to open files etc."""
        self.params = params
        self.context = context
        if not hasattr(self, "id"):
            self.id = self.name
        self.reset()

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
    def series_added(cls, params: FilterParams) -> tuple[SeriesDef, ...]:
        """The series a stage with ``params`` adds: ``adds_series`` unless a parameter renames
        them."""
        return cls.adds_series

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
