"""Events in HDF5, in DSEC's layout (``pip install 'evchain[hdf5]'``): source ``hdf5`` and sink
``hdf5_writer``, and the functions :func:`read_hdf5` and :func:`write_hdf5`.

Layout (the one of DSEC, so DSEC's own loaders and slicer read evchain's files, and evchain reads
theirs)::

    /events/x  uint16    /events/y  uint16    /events/p  uint8, 0 = OFF, 1 = ON
    /events/t  int64, µs after t_offset
    /t_offset  int64 scalar, µs: the stream time of t = 0
    /ms_to_idx uint64 [n_ms]: ms_to_idx[i] = index of the first event with t >= i * 1000
    attributes of /events: width, height (and f, cx, cy when known; DSEC has none)

``t_offset`` and ``ms_to_idx`` sit beside the events group (at the root for ``events``). DSEC
stores ``t`` as uint32 (71.6 minutes at most); evchain writes int64, which DSEC's slicer casts
alike. The writer stores ``t_offset`` = the start of the first packet and ``ms_to_idx`` up to
the end of the last packet, so DSEC's ``EventSlicer.get_events`` answers any window of the
stream. Datasets are chunked and compressed (``compression``: Blosc with zstd as in DSEC's files,
gzip, or none); Blosc needs ``hdf5plugin``, which the ``hdf5`` extra installs.

Reading adds ``t_offset`` (when present) to ``t`` and maps polarity 0/1 to -1/+1; files of
earlier evchain versions (``p`` -1/+1, no ``t_offset``) read as they are. Any other polarity
value, or 0 and -1 in one file, is a :class:`DataError` naming the dataset and the event. The
writer appends packet by packet and renames the finished file from ``NAME.partial`` only on
success.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, Geometry
from evchain.errors import ConfigError, DataError
from evchain.io.atomic import AtomicFile
from evchain.io.slicing import slice_stream

COLUMNS = ("x", "y", "t", "p")
DTYPES = {"x": np.uint16, "y": np.uint16, "t": np.int64, "p": np.uint8}
WRITE_BLOCK_EVENTS = 1 << 20  # events buffered by the writer between appends
READ_CHUNK_EVENTS = 1 << 20
CHUNK_ROWS = 1 << 16  # HDF5 chunk of every dataset

Compression = Literal["blosc", "gzip", "none"]


def _h5py():
    try:
        import h5py
    except ImportError:
        raise ConfigError("HDF5 needs h5py: pip install 'evchain[hdf5]'") from None
    try:  # registers Blosc and the other filters DSEC-style files use
        import hdf5plugin  # noqa: F401
    except ImportError:
        pass
    return h5py


def compression_options(compression: Compression) -> dict:
    """h5py ``create_dataset`` keywords for a compression name."""
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 1}
    if compression == "blosc":
        try:
            import hdf5plugin
        except ImportError:
            raise ConfigError("compression 'blosc' needs hdf5plugin: pip install "
                              "'evchain[hdf5]' (or set compression: gzip)",
                              key="hdf5_writer.compression") from None
        return dict(hdf5plugin.Blosc(cname="zstd", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))
    return {}


# ---------------------------------------------------------------------------------------------
# writing


class DsecWriter:
    """Appends packets to an open ``h5py.File`` in DSEC's layout; :meth:`finish` writes
    ``t_offset`` and ``ms_to_idx``. ``t_offset`` is the first packet's ``t_start``."""

    def __init__(self, h5file, geometry: Geometry | None, compression: Compression = "blosc"):
        self.file = h5file
        opts = compression_options(compression)
        g = h5file.create_group("events")
        if geometry is not None:
            _geometry_attrs(g, geometry)
        for c in COLUMNS:
            g.create_dataset(c, shape=(0,), maxshape=(None,), dtype=DTYPES[c],
                             chunks=(CHUNK_ROWS,), **opts)
        self.events = g
        self.opts = opts
        self.t_offset: int | None = None
        self.t_end: int | None = None
        self.written = 0
        self.ms_to_idx: list[np.ndarray] = []
        self.next_ms = 0
        self.pending: list[EventPacket] = []
        self.n_pending = 0

    def append(self, packet: EventPacket) -> None:
        if self.t_offset is None:
            self.t_offset = int(packet.t_start)
            if "width" not in self.events.attrs:  # no geometry known when the file was made
                _geometry_attrs(self.events, packet.geometry)
        self.t_end = int(packet.t_end)
        if len(packet):
            self.pending.append(packet)
            self.n_pending += len(packet)
            if self.n_pending >= WRITE_BLOCK_EVENTS:
                self._write_pending()

    def _write_pending(self) -> None:
        """Append the buffered packets: one resize and write per column and block, since
        h5py's per-call cost is far above a 10 ms packet's worth of copying."""
        if not self.pending:
            return
        n = self.n_pending
        t = np.concatenate([p.t for p in self.pending]) - self.t_offset
        cols = {"x": np.concatenate([p.x for p in self.pending]),
                "y": np.concatenate([p.y for p in self.pending]),
                "t": t,
                "p": (np.concatenate([p.p for p in self.pending]) > 0).astype(np.uint8)}
        for c in COLUMNS:
            d = self.events[c]
            d.resize((len(d) + n,))
            d[-n:] = cols[c]
        # every ms up to the block's last event is settled: later events come at or after it
        ms = np.arange(self.next_ms, int(t[-1]) // 1000 + 1, dtype=np.int64)
        self.ms_to_idx.append(self.written + np.searchsorted(t, ms * 1000, side="left"))
        self.next_ms += len(ms)
        self.written += n
        self.pending, self.n_pending = [], 0

    def finish(self) -> None:
        """Write what is pending, ``t_offset`` and ``ms_to_idx`` (up to the end of the last
        packet: ``ceil((t_end - t_offset) / 1000) + 1`` entries)."""
        self._write_pending()
        t_offset = 0 if self.t_offset is None else self.t_offset
        end_rel = 0 if self.t_end is None else self.t_end - t_offset
        n_ms = max(-(-end_rel // 1000) + 1, self.next_ms)
        tail = np.full(n_ms - self.next_ms, self.written, np.int64)
        ms_to_idx = np.concatenate([*self.ms_to_idx, tail]).astype(np.uint64)
        self.file.create_dataset("ms_to_idx", data=ms_to_idx, **self.opts)
        self.file.create_dataset("t_offset", data=np.int64(t_offset))


def _geometry_attrs(group, geometry: Geometry) -> None:
    group.attrs.update({"width": geometry.width, "height": geometry.height, "cx": geometry.cx,
                        "cy": geometry.cy, **({"f": geometry.f} if geometry.f else {})})


def write_hdf5(path: str | Path, events: EventPacket, compression: Compression = "blosc"
               ) -> Path:
    """Write one packet to ``path`` in DSEC's layout, atomically (``path.partial`` until
    complete)."""
    h5py = _h5py()
    out = AtomicFile.reserve(path)
    try:
        with h5py.File(out.tmp, "w") as f:
            w = DsecWriter(f, events.geometry, compression)
            w.append(events)
            w.finish()
    except BaseException:
        out.abort()
        raise
    out.commit()
    return Path(path)


# ---------------------------------------------------------------------------------------------
# reading


class DsecReader:
    """An open HDF5 event file: checks the layout, reads events in chunks (``t_offset`` added,
    polarity as ±1)."""

    def __init__(self, path: str | Path, group: str = "events", width: int | None = None,
                 height: int | None = None):
        h5py = _h5py()
        self.path = Path(path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: file not found")
        try:
            self.file = h5py.File(self.path, "r")
        except OSError as exc:
            raise DataError(f"{self.path}: not an HDF5 file ({exc})") from None
        try:
            self._check(group, width, height)
        except BaseException:
            self.close()
            raise
        self.seen_zero = self.seen_minus = False

    def _check(self, group: str, width: int | None, height: int | None) -> None:
        if group not in self.file:
            raise DataError(f"{self.path}: no group {group!r}; expected datasets "
                            f"{group}/x, y, t, p")
        self.name = group
        self.group = self.file[group]
        missing = [c for c in COLUMNS if c not in self.group]
        if missing:
            raise DataError(f"{self.path}: group {group!r} lacks datasets {missing}")
        shapes = {c: self.group[c].shape for c in COLUMNS}
        flat = {c: shape for c, shape in shapes.items() if len(shape) != 1}
        if flat:
            raise DataError(f"{self.path}: datasets {group}/{', '.join(flat)} must be 1-D "
                            f"(one value per event), got shapes "
                            f"{', '.join(f'{c} {shape}' for c, shape in flat.items())}")
        lengths = {c: shape[0] for c, shape in shapes.items()}
        if len(set(lengths.values())) != 1:
            raise DataError(f"{self.path}: datasets differ in length: {lengths}")
        self.n = lengths["t"]
        for c in COLUMNS:
            kind = self.group[c].dtype.kind
            if kind not in "uib":
                raise DataError(f"{self.path}: dataset {group}/{c} has dtype "
                                f"{self.group[c].dtype}; expected integers (t in µs)")
            try:
                self.group[c][:1]
            except OSError as exc:
                raise DataError(f"{self.path}: cannot read {group}/{c} ({exc}); a file compressed "
                                "with Blosc or another HDF5 plugin filter needs hdf5plugin: pip "
                                "install 'evchain[hdf5]'") from None
        self.t_offset = self._t_offset()
        attrs = dict(self.group.attrs)
        width = width or attrs.get("width")
        height = height or attrs.get("height")
        if width is None or height is None:
            raise DataError(f"{self.path}: no width/height attributes on {group!r} (DSEC's "
                            "files have none: their cameras are 640x480); give the parameters "
                            "width and height")
        self.geometry = Geometry(int(width), int(height), *(
            float(attrs[k]) if k in attrs else None for k in ("f", "cx", "cy")))

    def _t_offset(self) -> int:
        parent = self.group.parent
        if "t_offset" not in parent:
            return 0
        d = parent["t_offset"]
        value = np.asarray(d[()]).reshape(-1)
        if len(value) != 1 or value.dtype.kind not in "ui":
            raise DataError(f"{self.path}: dataset {d.name} must hold one integer (µs), got "
                            f"shape {d.shape} dtype {d.dtype}")
        return int(value[0])

    def time_span_us(self) -> tuple[int, int] | None:
        t = self.group["t"]
        if not self.n:
            return None
        return int(t[0]) + self.t_offset, int(t[-1]) + self.t_offset + 1

    def read(self, start: int, stop: int, before: np.ndarray) -> dict[str, np.ndarray]:
        """Events ``[start, stop)`` as evchain columns; ``before``: the previous chunk's last
        time (empty for the first), for the order check."""
        g = self.geometry
        name = self.name
        x = self.group["x"][start:stop]
        y = self.group["y"][start:stop]
        t = self.group["t"][start:stop].astype(np.int64) + self.t_offset
        raw = self.group["p"][start:stop]
        p = self._polarity(raw, start)
        back = np.diff(np.concatenate([before[-1:], t])) < 0
        if back.any():
            i = start + int(np.argmax(back)) + (0 if len(before) else 1)
            raise DataError(f"{self.path}: {name}/t: event {i} goes back in time")
        bad = (x < 0) | (y < 0) | (x >= g.width) | (y >= g.height)
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"{self.path}: event {start + i} at ({x[i]}, {y[i]}) outside the "
                            f"{g.width}x{g.height} sensor")
        return {"x": x.astype(np.uint16), "y": y.astype(np.uint16), "t": t, "p": p}

    def _polarity(self, raw: np.ndarray, start: int) -> np.ndarray:
        """0/1 (DSEC) or -1/+1 (earlier evchain files) as int8 ±1; anything else is an error."""
        if raw.dtype.kind == "b":
            return np.where(raw, 1, -1).astype(np.int8)
        if len(raw):
            lo, hi = int(raw.min()), int(raw.max())
            if lo < -1 or hi > 1:
                i = int(np.argmax((raw < -1) | (raw > 1)))
                raise DataError(f"{self.path}: {self.name}/p: event {start + i} has polarity "
                                f"{raw[i]}; expected 0/1 (DSEC: 0 OFF, 1 ON) or -1/+1")
            self.seen_minus |= lo == -1
            self.seen_zero |= bool((raw == 0).any())
            if self.seen_minus and self.seen_zero:
                raise DataError(f"{self.path}: {self.name}/p holds both 0 and -1 (by event "
                                f"{start + len(raw) - 1}); expected 0/1 (DSEC) or -1/+1, not a "
                                "mix")
        return np.where(raw > 0, 1, -1).astype(np.int8)

    def chunks(self, chunk: int = READ_CHUNK_EVENTS) -> Iterator[dict[str, np.ndarray]]:
        last = np.zeros(0, np.int64)
        for start in range(0, self.n, chunk):
            cols = self.read(start, min(start + chunk, self.n), last)
            last = cols["t"][-1:]
            yield cols

    def close(self) -> None:
        f = getattr(self, "file", None)
        if f is not None:
            f.close()
            self.file = None


def read_hdf5(path: str | Path, group: str = "events", width: int | None = None,
              height: int | None = None) -> EventPacket:
    """A whole file as one packet (slice ``[t0, t_last + 1)``), times with ``t_offset`` added."""
    r = DsecReader(path, group, width, height)
    try:
        parts = list(r.chunks())
    finally:
        r.close()
    if not parts:
        return EventPacket.empty(r.geometry, r.t_offset, r.t_offset)
    cols = {c: np.concatenate([p[c] for p in parts]) for c in COLUMNS}
    return EventPacket(geometry=r.geometry, t_start=int(cols["t"][0]),
                       t_end=int(cols["t"][-1]) + 1, **cols)


# ---------------------------------------------------------------------------------------------
# stages


class Hdf5Source(Filter):
    """Read events from an HDF5 file in DSEC's layout (events/x, y, t, p; t_offset added)."""

    name = "hdf5"
    produces = EventPacket
    input_paths = ("path",)

    class Params(FilterParams):
        path: str = Field(description="HDF5 file")
        group: str = Field("events", description="group holding x, y, t, p (t_offset and "
                                                 "ms_to_idx beside it)")
        packet_us: int = Field(10_000, ge=1, description="slice duration of each packet")
        width: int | None = Field(None, ge=1, description="sensor width if the file lacks it")
        height: int | None = Field(None, ge=1, description="sensor height if the file lacks it")

    def setup(self, params, context):
        self.reader = DsecReader(params.path, params.group, params.width, params.height)
        self.path = self.reader.path
        context.geometry = self.reader.geometry
        super().setup(params, context)

    def time_span_us(self):
        return self.reader.time_span_us()

    def packets(self) -> Iterator[EventPacket]:
        r = self.reader
        r.seen_zero = r.seen_minus = False
        yield from slice_stream(r.chunks(), self.context.geometry, self.params.packet_us)

    def close(self):
        r = getattr(self, "reader", None)
        if r is not None:
            r.close()


class Hdf5Writer(Filter):
    """Write events to HDF5 in DSEC's layout (events/x, y, t, p; t_offset; ms_to_idx); pass
    them on."""

    name = "hdf5_writer"
    consumes = EventPacket
    output_paths = ("path",)

    class Params(FilterParams):
        path: str = Field("events.h5", description="output file, relative to the run folder")
        compression: Compression = Field(
            "blosc", description="blosc (zstd, as DSEC's files; needs hdf5plugin), gzip or none")

    def setup(self, params, context):
        self.h5py = _h5py()
        compression_options(params.compression)  # fails here, not after the first packet
        super().setup(params, context)

    def reset(self):
        self.close()
        self.out = AtomicFile.reserve(self.context.output_path(self.params.path))
        self.file = self.h5py.File(self.out.tmp, "w")
        self.writer = DsecWriter(self.file, self.context.geometry, self.params.compression)

    def process(self, packet: EventPacket) -> EventPacket:
        self.writer.append(packet)
        return packet

    def flush(self):
        self.writer.finish()
        self.file.close()
        self.file = None
        self.out.commit()
        return None

    def close(self):
        f = getattr(self, "file", None)
        if f is not None:
            f.close()
            self.file = None
            self.out.abort()
