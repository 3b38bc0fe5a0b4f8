"""Typed packets: contiguous numpy columns covering one time slice.

Invariants (checked by :meth:`Packet.validate`, at sources and between filters in debug runs):

* every packet carries the sensor :class:`Geometry` and its slice ``[t_start, t_end)`` in integer
  microseconds, ``t_start <= t_end``;
* ``FramePacket``: ``frames`` float32 ``[n, H, W]``, finite and ``>= 0`` (linear intensity, HDR
  allowed); ``t`` int64 ``[n]``, strictly increasing, inside the slice; ``ApsFramePacket`` adds
  ``t_exposure_start`` int64 ``[n]`` (``<= t``, the exposure's end);
* ``EventPacket``: ``x``, ``y`` uint16 (``x < width``, ``y < height``, top-left origin), ``t``
  int64 µs non-decreasing and inside the slice, ``p`` int8 in {+1 ON, -1 OFF}; all the same length;
* ``FlowPacket``: an ``EventPacket`` plus ``vx``, ``vy`` float32 in px/s, finite;
* ``series``: named time series (numpy structured arrays with an int64 field ``t``) that filters
  append to, e.g. ``foe`` (t, x, y, support, total), each defined in :mod:`evchain.core.series`.
  A packet's series hold only the entries of its slice.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar, Self

import numpy as np

from evchain.errors import DataError

Series = dict[str, np.ndarray]


@dataclass(frozen=True)
class Geometry:
    """Sensor size in pixels and, when known, pinhole intrinsics (f, cx, cy) in pixels.

    The principal point defaults to the image centre, ``((W-1)/2, (H-1)/2)``, since pixel
    coordinates have their origin at the top-left pixel's centre.
    """

    width: int
    height: int
    f: float | None = None
    cx: float | None = None
    cy: float | None = None

    def __post_init__(self):
        if self.width <= 0 or self.height <= 0:
            raise DataError(f"sensor geometry must be positive, got {self.width}x{self.height}")
        if self.cx is None:
            object.__setattr__(self, "cx", (self.width - 1) / 2.0)
        if self.cy is None:
            object.__setattr__(self, "cy", (self.height - 1) / 2.0)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width), the numpy shape of one frame."""
        return (self.height, self.width)


@dataclass(frozen=True, eq=False)
class Packet:
    """Base of all packets: geometry, time slice and series. Immutable; use :meth:`replace`."""

    geometry: Geometry
    t_start: int
    t_end: int
    series: Series = field(default_factory=dict)

    columns: ClassVar[dict[str, type]] = {}

    def __len__(self) -> int:
        return len(self.t)

    def replace(self, **changes) -> Self:
        """A copy with some fields changed (columns are shared, not copied). Copies the
        instance dict instead of calling ``__init__`` as :func:`dataclasses.replace` does:
        every filter calls this once per packet, and it is 3x faster."""
        fields = _field_names(type(self))
        for name in changes:
            if name not in fields:
                raise TypeError(f"{type(self).__name__} has no field {name!r}")
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def with_series(self, name: str, entries: np.ndarray) -> Self:
        """A copy with ``entries`` appended to series ``name``."""
        series = dict(self.series)
        series[name] = entries if name not in series else np.concatenate([series[name], entries])
        return self.replace(series=series)

    def validate(self, where: str = "packet") -> Self:
        """Check the invariants of the module docstring; a :class:`DataError` names ``where``."""
        if self.t_start > self.t_end:
            raise DataError(f"{where}: slice start {self.t_start} us after end {self.t_end} us")
        n = None
        for name, dtype in self.columns.items():
            col = getattr(self, name)
            if not isinstance(col, np.ndarray) or col.dtype != np.dtype(dtype):
                got = getattr(col, "dtype", type(col).__name__)
                raise DataError(f"{where}: column {name!r} must be {np.dtype(dtype)}, got {got}")
            if name != "frames":
                if col.ndim != 1:
                    raise DataError(f"{where}: column {name!r} must be 1-D, got shape {col.shape}")
                if n is None:
                    n = len(col)
                elif len(col) != n:
                    raise DataError(f"{where}: column {name!r} has {len(col)} rows, expected {n}")
        t = self.t
        if len(t):
            if t[0] < self.t_start or t[-1] >= self.t_end:
                raise DataError(f"{where}: timestamps {t[0]}..{t[-1]} us outside the slice "
                                f"[{self.t_start}, {self.t_end})")
        for name, entries in self.series.items():
            if entries.dtype.names is None or "t" not in entries.dtype.names:
                raise DataError(f"{where}: series {name!r} must be a structured array with field t")
        self._validate_more(where)
        return self

    def _validate_more(self, where: str) -> None:
        pass

    @classmethod
    def concat(cls, packets: list[Self]) -> Self:
        """Join packets of consecutive slices into one (series concatenated by name)."""
        if not packets:
            raise ValueError("concat needs at least one packet")
        first = packets[0]
        cols = {name: np.concatenate([getattr(p, name) for p in packets]) for name in cls.columns}
        series: Series = {}
        for p in packets:
            for name, entries in p.series.items():
                series[name] = (np.concatenate([series[name], entries]) if name in series
                                else entries)
        return cls(geometry=first.geometry, t_start=first.t_start, t_end=packets[-1].t_end,
                   series=series, **cols)


def _empty_columns(columns: dict[str, type]) -> dict[str, np.ndarray]:
    return {name: np.zeros(0, dtype) for name, dtype in columns.items()}


@dataclass(frozen=True, eq=False)
class FramePacket(Packet):
    """Frames of linear intensity (float32 ``[n, H, W]``) at times ``t`` (int64 µs)."""

    frames: np.ndarray = None  # type: ignore[assignment]
    t: np.ndarray = None  # type: ignore[assignment]

    columns: ClassVar[dict[str, type]] = {"frames": np.float32, "t": np.int64}

    def _validate_more(self, where: str) -> None:
        f = self.frames
        if f.ndim != 3 or f.shape[1:] != self.geometry.shape or len(f) != len(self.t):
            raise DataError(f"{where}: frames must have shape [n={len(self.t)}, "
                            f"H={self.geometry.height}, W={self.geometry.width}], got {f.shape}")
        if len(self.t) > 1 and np.any(np.diff(self.t) <= 0):
            i = int(np.argmax(np.diff(self.t) <= 0))
            raise DataError(f"{where}: frame times must increase, frame {i + 1} at "
                            f"{self.t[i + 1]} us follows {self.t[i]} us")
        if f.size and not (np.isfinite(f).all() and f.min() >= 0):
            raise DataError(f"{where}: frames must be finite and >= 0 (linear intensity)")

    @classmethod
    def empty(cls, geometry: Geometry, t_start: int, t_end: int) -> FramePacket:
        return cls(geometry=geometry, t_start=t_start, t_end=t_end,
                   frames=np.zeros((0, *geometry.shape), np.float32), t=np.zeros(0, np.int64))


@dataclass(frozen=True, eq=False)
class ApsFramePacket(FramePacket):
    """Frames of an exposure (the ``aps`` sensor): ``t`` is when each frame's exposure ended
    (its last row's, with a rolling shutter: when the frame is complete), ``t_exposure_start``
    (int64 µs) when it began (its first row's). ``frames`` hold digital numbers as a fraction
    of full scale, in [0, 1]."""

    t_exposure_start: np.ndarray = None  # type: ignore[assignment]

    columns: ClassVar[dict[str, type]] = {**FramePacket.columns, "t_exposure_start": np.int64}

    def _validate_more(self, where: str) -> None:
        super()._validate_more(where)
        s = self.t_exposure_start
        if s.shape != self.t.shape or np.any(s > self.t):
            raise DataError(f"{where}: t_exposure_start must have one entry per frame, none "
                            "after the frame's t (the end of its exposure)")

    @classmethod
    def empty(cls, geometry: Geometry, t_start: int, t_end: int) -> ApsFramePacket:
        return cls(geometry=geometry, t_start=t_start, t_end=t_end,
                   frames=np.zeros((0, *geometry.shape), np.float32), t=np.zeros(0, np.int64),
                   t_exposure_start=np.zeros(0, np.int64))


@dataclass(frozen=True, eq=False)
class EventPacket(Packet):
    """DVS events: ``x``, ``y`` (uint16), ``t`` (int64 µs, non-decreasing), ``p`` (int8 ±1)."""

    x: np.ndarray = None  # type: ignore[assignment]
    y: np.ndarray = None  # type: ignore[assignment]
    t: np.ndarray = None  # type: ignore[assignment]
    p: np.ndarray = None  # type: ignore[assignment]

    columns: ClassVar[dict[str, type]] = {"x": np.uint16, "y": np.uint16, "t": np.int64,
                                          "p": np.int8}

    def _validate_more(self, where: str) -> None:
        if len(self) == 0:
            return
        if self.x.max() >= self.geometry.width or self.y.max() >= self.geometry.height:
            i = int(np.argmax((self.x >= self.geometry.width) | (self.y >= self.geometry.height)))
            raise DataError(f"{where}: event {i} at ({self.x[i]}, {self.y[i]}) outside the "
                            f"{self.geometry.width}x{self.geometry.height} sensor")
        if len(self) > 1 and np.any(np.diff(self.t) < 0):
            i = int(np.argmax(np.diff(self.t) < 0))
            raise DataError(f"{where}: event times must not decrease, event {i + 1} at "
                            f"{self.t[i + 1]} us follows {self.t[i]} us")
        if not np.all(np.abs(self.p) == 1):
            raise DataError(f"{where}: polarity must be +1 (ON) or -1 (OFF)")

    @classmethod
    def empty(cls, geometry: Geometry, t_start: int, t_end: int) -> Self:
        return cls(geometry=geometry, t_start=t_start, t_end=t_end,
                   **_empty_columns(cls.columns))

    def select(self, mask_or_index: np.ndarray) -> Self:
        """The events picked by a boolean mask or an index array, same slice and series."""
        return self.replace(**{name: getattr(self, name)[mask_or_index] for name in self.columns})

    def to_structured(self) -> np.ndarray:
        """One numpy structured array with a field per column (for tonic and friends)."""
        out = np.empty(len(self), dtype=[(n, np.dtype(d)) for n, d in self.columns.items()])
        for name in self.columns:
            out[name] = getattr(self, name)
        return out

    @classmethod
    def from_structured(cls, array: np.ndarray, geometry: Geometry, t_start: int | None = None,
                        t_end: int | None = None) -> Self:
        """Build a packet from a structured array with the columns' field names.

        The slice defaults to ``[t[0], t[-1] + 1)``. Fields are cast to the column dtypes.
        """
        missing = [n for n in cls.columns if n not in (array.dtype.names or ())]
        if missing:
            raise DataError(f"structured array lacks fields {missing}; has {array.dtype.names}")
        cols = {n: np.ascontiguousarray(array[n], dtype=d) for n, d in cls.columns.items()}
        t = cols["t"]
        if t_start is None:
            t_start = int(t[0]) if len(t) else 0
        if t_end is None:
            t_end = int(t[-1]) + 1 if len(t) else t_start
        return cls(geometry=geometry, t_start=t_start, t_end=t_end, **cols).validate()


@dataclass(frozen=True, eq=False)
class FlowPacket(EventPacket):
    """Events that got a flow estimate, with ``vx``, ``vy`` (float32, px/s) and ``t_edge``.

    Normal flow (the component along the local edge normal) unless the producing filter says
    it gives full flow. ``t_edge`` (int64 µs, at most ``t``) is when the edge that fired the
    event reached its pixel: the first event of the pixel's current run of same-polarity
    events, among all events the flow stage received (:mod:`evchain.core.edge_arrival`). An
    edge crossing a pixel fires a run of events spread over the crossing, and the flow stage
    keeps only some of them, so comparing two pixels' flow-event times mixes early and late
    events of their crossings; their arrival times compare like with like. A producer that
    does not track runs gives ``t`` (the default).
    """

    vx: np.ndarray = None  # type: ignore[assignment]
    vy: np.ndarray = None  # type: ignore[assignment]
    t_edge: np.ndarray = None  # type: ignore[assignment]

    columns: ClassVar[dict[str, type]] = {**EventPacket.columns, "vx": np.float32,
                                          "vy": np.float32, "t_edge": np.int64}

    def __post_init__(self) -> None:
        if self.t_edge is None and self.t is not None:
            object.__setattr__(self, "t_edge", self.t)

    def _validate_more(self, where: str) -> None:
        super()._validate_more(where)
        if len(self) and not (np.isfinite(self.vx).all() and np.isfinite(self.vy).all()):
            raise DataError(f"{where}: flow must be finite")
        if len(self) and np.any(self.t_edge > self.t):
            i = int(np.argmax(self.t_edge > self.t))
            raise DataError(f"{where}: event {i}'s edge arrival t_edge {self.t_edge[i]} us is "
                            f"after its time {self.t[i]} us")

    @classmethod
    def from_events(cls, events: EventPacket, index: np.ndarray, vx: np.ndarray,
                    vy: np.ndarray, t_edge: np.ndarray | None = None) -> FlowPacket:
        """Flow for the events at ``index`` of ``events`` (same slice and series);
        ``t_edge``, when given, holds the arrival time of every event of ``events``."""
        return cls(geometry=events.geometry, t_start=events.t_start, t_end=events.t_end,
                   series=events.series, x=events.x[index], y=events.y[index],
                   t=events.t[index], p=events.p[index], vx=np.asarray(vx, np.float32),
                   vy=np.asarray(vy, np.float32),
                   t_edge=None if t_edge is None else t_edge[index])


_FIELDS: dict[type, frozenset[str]] = {}


def _field_names(cls: type) -> frozenset[str]:
    names = _FIELDS.get(cls)
    if names is None:
        names = _FIELDS[cls] = frozenset(f.name for f in dataclasses.fields(cls))
    return names
