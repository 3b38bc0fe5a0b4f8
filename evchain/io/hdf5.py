"""Events in HDF5 (``pip install 'evchain[hdf5]'``): source ``hdf5`` and sink ``hdf5_writer``.

Layout (the one of DSEC and most event datasets, so their files read as they are)::

    /events/x  uint16     /events/y  uint16     /events/t  int64 (µs)     /events/p  int8 or uint8
    attributes of /events: width, height (and f, cx, cy when known)

Polarity is written as +1/-1; on reading, 0/1 (the DSEC convention) is mapped to -1/+1.
Datasets are chunked and gzip-compressed; the writer appends packet by packet and renames the
finished file from ``NAME.partial`` only on success.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, Geometry
from evchain.errors import ConfigError, DataError
from evchain.io.atomic import AtomicFile
from evchain.io.slicing import slice_stream

COLUMNS = ("x", "y", "t", "p")
WRITE_BLOCK_EVENTS = 1 << 20  # events buffered by the writer between appends


def _h5py():
    try:
        import h5py
    except ImportError:
        raise ConfigError("HDF5 needs h5py: pip install 'evchain[hdf5]'") from None
    return h5py


class Hdf5Source(Filter):
    """Read events from an HDF5 file with datasets events/x, y, t, p (DSEC layout)."""

    name = "hdf5"
    produces = EventPacket
    input_paths = ("path",)

    class Params(FilterParams):
        path: str = Field(description="HDF5 file")
        group: str = Field("events", description="group holding x, y, t, p")
        packet_us: int = Field(10_000, ge=1, description="slice duration of each packet")
        width: int | None = Field(None, ge=1, description="sensor width if the file lacks it")
        height: int | None = Field(None, ge=1, description="sensor height if the file lacks it")

    def setup(self, params, context):
        h5py = _h5py()
        self.path = Path(params.path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: file not found")
        try:
            self.file = h5py.File(self.path, "r")
        except OSError as exc:
            raise DataError(f"{self.path}: not an HDF5 file ({exc})") from None
        if params.group not in self.file:
            raise DataError(f"{self.path}: no group {params.group!r}; expected datasets "
                            f"{params.group}/x, y, t, p")
        self.group = self.file[params.group]
        missing = [c for c in COLUMNS if c not in self.group]
        if missing:
            raise DataError(f"{self.path}: group {params.group!r} lacks datasets {missing}")
        shapes = {c: self.group[c].shape for c in COLUMNS}
        flat = {c: shape for c, shape in shapes.items() if len(shape) != 1}
        if flat:
            raise DataError(f"{self.path}: datasets {params.group}/{', '.join(flat)} must be 1-D "
                            f"(one value per event), got shapes "
                            f"{', '.join(f'{c} {shape}' for c, shape in flat.items())}")
        lengths = {c: shape[0] for c, shape in shapes.items()}
        if len(set(lengths.values())) != 1:
            raise DataError(f"{self.path}: datasets differ in length: {lengths}")
        attrs = dict(self.group.attrs)
        width = params.width or attrs.get("width")
        height = params.height or attrs.get("height")
        if width is None or height is None:
            raise DataError(f"{self.path}: no width/height attributes on {params.group!r}; "
                            "give the parameters width and height")
        context.geometry = Geometry(int(width), int(height), *(
            float(attrs[k]) if k in attrs else None for k in ("f", "cx", "cy")))
        super().setup(params, context)

    def time_span_us(self):
        t = self.group["t"]
        return (int(t[0]), int(t[-1]) + 1) if len(t) else None

    def packets(self) -> Iterator[EventPacket]:
        n, chunk = len(self.group["t"]), 1 << 20
        state = {"last": np.zeros(0, np.int64)}

        def chunks():
            for start in range(0, n, chunk):
                cols = self._read(start, min(start + chunk, n), state["last"])
                state["last"] = cols["t"][-1:]
                yield cols

        yield from slice_stream(chunks(), self.context.geometry, self.params.packet_us)

    def _read(self, start: int, stop: int, before: np.ndarray) -> dict[str, np.ndarray]:
        g = self.context.geometry
        x = self.group["x"][start:stop].astype(np.uint16)
        y = self.group["y"][start:stop].astype(np.uint16)
        t = self.group["t"][start:stop].astype(np.int64)
        p = np.where(self.group["p"][start:stop] > 0, 1, -1).astype(np.int8)
        back = np.diff(np.concatenate([before[-1:], t])) < 0
        if back.any():
            i = start + int(np.argmax(back)) - (0 if len(before) else -1)
            raise DataError(f"{self.path}: event {i}: timestamp goes backwards")
        bad = (x >= g.width) | (y >= g.height)
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"{self.path}: event {start + i} at ({x[i]}, {y[i]}) outside the "
                            f"{g.width}x{g.height} sensor")
        return {"x": x, "y": y, "t": t, "p": p}

    def close(self):
        f = getattr(self, "file", None)
        if f is not None:
            f.close()
            self.file = None


class Hdf5Writer(Filter):
    """Write events to HDF5 (events/x, y, t, p with width/height attributes); pass them on."""

    name = "hdf5_writer"
    consumes = EventPacket
    output_paths = ("path",)

    class Params(FilterParams):
        path: str = Field("events.h5", description="output file, relative to the run folder")
        compression: bool = Field(True, description="gzip-compress the datasets")

    def setup(self, params, context):
        self.h5py = _h5py()
        super().setup(params, context)

    def reset(self):
        self.close()
        self.out = AtomicFile.reserve(self.context.output_path(self.params.path))
        self.file = self.h5py.File(self.out.tmp, "w")
        g = self.file.create_group("events")
        geo = self.context.geometry
        if geo is not None:
            g.attrs.update({"width": geo.width, "height": geo.height, "cx": geo.cx,
                            "cy": geo.cy, **({"f": geo.f} if geo.f else {})})
        kw = {"compression": "gzip", "compression_opts": 1} if self.params.compression else {}
        for c, dtype in EventPacket.columns.items():
            g.create_dataset(c, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(1 << 16,),
                             **kw)
        self.events = g
        self.pending: list[EventPacket] = []
        self.n_pending = 0

    def process(self, packet: EventPacket) -> EventPacket:
        if len(packet):
            self.pending.append(packet)
            self.n_pending += len(packet)
            if self.n_pending >= WRITE_BLOCK_EVENTS:
                self._write_pending()
        return packet

    def _write_pending(self) -> None:
        """Append the buffered packets: one resize and write per column and block, since
        h5py's per-call cost is far above a 10 ms packet's worth of copying."""
        if not self.pending:
            return
        n = self.n_pending
        for c in COLUMNS:
            d = self.events[c]
            d.resize((len(d) + n,))
            d[-n:] = np.concatenate([getattr(p, c) for p in self.pending])
        self.pending, self.n_pending = [], 0

    def flush(self):
        self._write_pending()
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
