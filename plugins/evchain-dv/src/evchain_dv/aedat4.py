"""AEDAT 4.0 (iniVation DV) event files through ``dv-processing``: ``aedat4`` and ``aedat4_writer``.

The file format itself (flatbuffers packets, LZ4/ZSTD compression, the trailing file data
table) is left entirely to ``dv_processing.io.MonoCameraRecording`` / ``MonoCameraWriter``;
this module only converts between their event stores and evchain packets:

* timestamps are int64 µs as in the file (DV writes absolute Unix time; kept as is);
* polarity ``True``/``False`` becomes ``+1``/``-1`` and back;
* the sensor size is the event stream's resolution (or the ``width``/``height`` parameters);
* IMU samples (DV's IMU stream, ``IMUS`` packets of ``dv::IMU``: int64 timestamp in µs,
  temperature in °C, accelerometer x, y, z in g, gyroscope x, y, z in deg/s, magnetometer in
  µT, in the axes of the camera's IMU chip as libcaer gives them) become the series ``imu`` in
  evchain's camera axes (:func:`evchain.io.davis_imu.camera_axes`: x and z negated, as jAER
  and the ROS driver do for DAVIS cameras); the magnetometer is dropped. The writer does the
  reverse.

Two quirks of dv-processing 2.0 shape the code: its writer aborts the whole process (a C++
``std::terminate``, not a Python exception) unless the output name ends in ``.aedat4``, and its
reader reports problems as ``RuntimeError`` with a C++ stack trace. So the sink checks the name
itself, writes ``NAME.partial`` through a ``.aedat4``-named symbolic link in a private temporary
folder, and both stages turn library errors into one-line :class:`DataError` messages that name
the file.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, Geometry
from evchain.core.series import IMU
from evchain.errors import ConfigError, DataError
from evchain.io.atomic import AtomicFile
from evchain.io.davis_imu import camera_axes, sensor_axes
from evchain.io.slicing import ImuSlicer, attach_imu, slice_stream
from pydantic import Field, field_validator

MAGIC = b"#!AER-DAT4.0"
COMPRESSIONS = {"none": "NONE", "lz4": "LZ4", "lz4_high": "LZ4_HIGH", "zstd": "ZSTD",
                "zstd_high": "ZSTD_HIGH"}


def _dv():
    try:
        import dv_processing
    except ImportError:
        raise ConfigError("AEDAT 4.0 needs dv-processing: pip install dv-processing") from None
    return dv_processing


def dv_message(exc: BaseException) -> str:
    """The useful part of a dv-processing error: no C++ source location, no stack trace."""
    lines = []
    for line in str(exc).splitlines():
        if line.startswith("Stacktrace"):
            break
        if re.match(r"^\S*\.(hpp|cpp|h)\(\d+\):", line.strip()):
            continue
        if line.strip():
            lines.append(line.strip())
    return " ".join(lines) or type(exc).__name__


def event_columns(a: np.ndarray, g: Geometry, where: str, done: int, last: int | None,
                  before: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """evchain's ``x, y, t, p`` columns of dv-processing's event array ``a`` (fields
    ``timestamp, x, y, polarity``, from ``EventStore.numpy()``), checked: time does not go
    backwards (``last``: the previous event's time, if any) and every event is on the sensor
    ``g``. Errors name ``where`` and the event's index in the stream (``done`` came before).
    ``before``: columns to put in front (converted with them, so nothing is copied twice)."""
    m = 0 if before is None else len(before["t"])
    n = len(a)
    cols = {"x": np.empty(m + n, np.uint16), "y": np.empty(m + n, np.uint16),
            "t": np.empty(m + n, np.int64), "p": np.empty(m + n, np.int8)}
    if m:
        for c, v in cols.items():
            v[:m] = before[c]
    t, x, y = cols["t"][m:], cols["x"][m:], cols["y"][m:]
    t[:] = a["timestamp"]
    if n and ((last is not None and t[0] < last) or np.any(t[1:] < t[:-1])):
        back = np.diff(t if last is None else np.concatenate([[last], t])) < 0
        i = done + int(np.argmax(back)) + (1 if last is None else 0)
        raise DataError(f"{where}: event {i}: timestamp goes backwards")
    x[:] = a["x"]  # a negative int16 becomes >= 32768: off any sensor
    y[:] = a["y"]
    if n and (x.max() >= g.width or y.max() >= g.height):
        i = int(np.argmax((x >= g.width) | (y >= g.height)))
        raise DataError(f"{where}: event {done + i} at ({a['x'][i]}, {a['y'][i]}) outside the "
                        f"{g.width}x{g.height} sensor")
    p = cols["p"][m:]
    np.greater(a["polarity"], 0, out=p.view(np.bool_))  # 1 or 0, then +1 or -1 in place
    p *= 2
    p -= 1
    return cols


#: the fields of dv::IMU that evchain reads, in the order of :func:`imu_entries`' columns
IMU_FIELDS = ("timestamp", "accelerometerX", "accelerometerY", "accelerometerZ",
              "gyroscopeX", "gyroscopeY", "gyroscopeZ", "temperature")


def imu_entries(batch, where: str, done: int) -> np.ndarray:
    """IMU series entries (camera axes) from a batch of dv-processing ``dv.IMU`` samples;
    a non-finite reading is a :class:`DataError` naming ``where``, the sample's index in the
    stream (``done`` came before) and the field."""
    rows = np.array([tuple(getattr(m, f) for f in IMU_FIELDS) for m in batch],
                    np.float64).reshape(-1, len(IMU_FIELDS))
    bad = ~np.isfinite(rows[:, 1:])
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise DataError(f"{where}: IMU sample {done + int(i)}: field {IMU_FIELDS[j + 1]} is "
                        f"{rows[i, j + 1]}; expected a finite reading")
    t = np.array([m.timestamp for m in batch], np.int64)
    return camera_axes(t, rows[:, 1:4], rows[:, 4:7], rows[:, 7])


class Aedat4Source(Filter):
    """Read events (and IMU samples) from an AEDAT 4.0 file (iniVation DV) with dv-processing.

    The file's IMU stream becomes the series ``imu`` (camera axes, g and deg/s; every packet
    carries it, empty where its slice has no sample); a file without one gives no series.
    Samples before the first event's slice or after the last one's are not delivered (counted
    in the metrics: ``imu_before_events``, ``imu_after_events``).
    """

    name = "aedat4"
    produces = EventPacket
    adds_series = (IMU,)
    input_paths = ("path",)

    class Params(FilterParams):
        path: str = Field(description="AEDAT 4.0 file (.aedat4)")
        stream: str = Field("events", description="name of the event stream in the file")
        camera: str | None = Field(None, description="camera name/serial, if the file holds "
                                   "several cameras")
        packet_us: int = Field(10_000, ge=1, description="slice duration of each packet")
        width: int | None = Field(None, ge=1, description="sensor width if the file lacks it")
        height: int | None = Field(None, ge=1, description="sensor height if the file lacks it")
        imu: bool = Field(True, description="read the file's IMU stream into the series imu "
                          "(camera axes, g and deg/s); false: ignore it")
        imu_stream: str | None = Field(None, description="name of the IMU stream; default: "
                                       "the file's only IMU stream, if it has one")

    @classmethod
    def series_added(cls, params):
        """``imu`` unless ``imu`` is false."""
        return (IMU,) if params.imu else ()

    def setup(self, params, context):
        dv = _dv()
        self.path = Path(params.path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: file not found" if not self.path.exists()
                            else f"{self.path}: not a file; expected an AEDAT 4.0 file")
        with open(self.path, "rb") as fh:
            head = fh.read(len(MAGIC))
        if head != MAGIC:
            hint = ("; this is an older AEDAT file: use the 'aedat' source"
                    if head.startswith(b"#!AER-DAT") else "")
            raise DataError(f"{self.path}: not an AEDAT 4.0 file: expected it to start with "
                            f"{MAGIC.decode()!r}, found {head[:12]!r}{hint}")
        try:
            if params.camera is None:
                self.recording = dv.io.MonoCameraRecording(str(self.path))
            else:
                self.recording = dv.io.MonoCameraRecording(str(self.path), params.camera)
        except RuntimeError as exc:
            raise DataError(f"{self.path}: cannot read the AEDAT 4.0 file: "
                            f"{dv_message(exc)}") from None
        names = list(self.recording.getStreamNames())
        if params.stream not in names or not self.recording.isStreamOfEventType(params.stream):
            events = [n for n in names if self.recording.isStreamOfEventType(n)]
            raise DataError(f"{self.path}: no event stream {params.stream!r}; event streams: "
                            f"{events or 'none'}, all streams: {names}")
        res = self.recording.getEventResolution(params.stream)
        width = params.width or (res[0] if res else None)
        height = params.height or (res[1] if res else None)
        if width is None or height is None:
            raise DataError(f"{self.path}: stream {params.stream!r} has no resolution; give the "
                            "parameters width and height")
        context.geometry = Geometry(int(width), int(height))
        self.imu_stream = self._find_imu_stream(params, names) if params.imu else None
        super().setup(params, context)

    def _find_imu_stream(self, params, names: list[str]) -> str | None:
        """The IMU stream to read: the one named, else the file's only one (None: none)."""
        rec = self.recording
        imus = [n for n in names if rec.isStreamOfImuType(n)]
        if params.imu_stream is None:
            if len(imus) > 1:
                raise DataError(f"{self.path}: several IMU streams {imus}; set imu_stream to "
                                "the one to read")
            return imus[0] if imus else None
        if params.imu_stream not in names:
            raise DataError(f"{self.path}: no IMU stream {params.imu_stream!r}; IMU streams: "
                            f"{imus or 'none'}, all streams: {names}")
        if params.imu_stream not in imus:
            raise DataError(f"{self.path}: stream {params.imu_stream!r} is not an IMU stream "
                            "(expected IMUS packets of dv::IMU: timestamp, temperature, "
                            f"accelerometer and gyroscope x, y, z); IMU streams: "
                            f"{imus or 'none'}")
        return params.imu_stream

    def time_span_us(self):
        try:
            t0, t1 = self.recording.getTimeRange()
        except RuntimeError:
            return None
        return int(t0), int(t1) + 1

    def packets(self) -> Iterator[EventPacket]:
        self.recording.resetSequentialRead()
        packets = slice_stream(self._chunks(), self.context.geometry, self.params.packet_us)
        imu = None if self.imu_stream is None else ImuSlicer(self._imu_batches(), str(self.path))
        metrics = {"file": str(self.path), "imu_stream": self.imu_stream}
        yield from attach_imu(packets, imu, metrics)
        self.context.metrics[self.id] = metrics

    def _next_batch(self, get, stream: str, what: str, done: int):
        """``get(stream)``, DV's next batch of the stream (None at its end); a packet DV cannot
        decode is a DataError naming the file, the stream and how many were read before it."""
        try:
            return get(stream)
        except RuntimeError as exc:
            raise DataError(f"{self.path}: after {what} {done}: cannot decode the next packet "
                            f"of stream {stream!r}: {dv_message(exc)}") from None

    def _imu_batches(self) -> Iterator[np.ndarray]:
        stream, done = self.imu_stream, 0
        while True:
            batch = self._next_batch(self.recording.getNextImuBatch, stream, "IMU sample", done)
            if batch is None:
                return
            yield imu_entries(batch, f"{self.path}: stream {stream!r}", done)
            done += len(batch)

    def _chunks(self) -> Iterator[dict[str, np.ndarray]]:
        g, stream = self.context.geometry, self.params.stream
        done, last = 0, None
        while True:
            batch = self._next_batch(self.recording.getNextEventBatch, stream, "event", done)
            if batch is None:
                return
            a = batch.numpy()
            if not len(a):
                continue
            yield event_columns(a, g, str(self.path), done, last)
            done += len(a)
            last = int(a["timestamp"][-1])

    def close(self):
        self.recording = None


class Aedat4Writer(Filter):
    """Write events to an AEDAT 4.0 file (iniVation DV) with dv-processing; pass them on.

    When the packets carry the series ``imu`` (decided when the file is opened: by the packets
    held until then), its samples go to an IMU stream ``imu`` in the IMU chip's axes as DV
    writes them (the reverse of the ``aedat4`` source's conversion; magnetometer 0).
    """

    name = "aedat4_writer"
    consumes = EventPacket
    optional_series = (IMU,)
    output_paths = ("path",)

    class Params(FilterParams):
        path: str = Field("events.aedat4", description="output file (must end in .aedat4), "
                          "relative to the run folder")
        camera: str = Field("evchain", description="camera name recorded in the file")
        compression: Literal["none", "lz4", "lz4_high", "zstd", "zstd_high"] = Field(
            "lz4", description="compression of the file's event packets")
        buffer_events: int = Field(1_000_000, ge=0, description="events held (16 bytes each) "
                                   "before the file is opened: dv-processing's writer thread "
                                   "busy-waits while a file is open, so shorter streams are "
                                   "written in one go by flush()")

        @field_validator("path")
        @classmethod
        def _aedat4_name(cls, value: str) -> str:
            if not value.endswith(".aedat4"):  # dv-processing aborts the process otherwise
                raise ValueError("must end in '.aedat4' (dv-processing writes no other names)")
            return value

    def setup(self, params, context):
        self.dv = _dv()
        self.writer = None
        super().setup(params, context)

    def reset(self):
        self._abort()
        self.path = self.context.output_path(self.params.path)
        self.out: AtomicFile | None = None  # a run has started (its output, once committed)
        self.geometry = None
        self.pending: list = []  # converted event stores not yet handed to the writer
        self.pending_events = 0
        self.pending_imu: list[np.ndarray] = []
        self.has_imu = False  # a packet so far carried the series imu
        self.imu_samples = 0

    def _open(self, geometry: Geometry) -> None:
        dv = self.dv
        if self.out.tmp.exists():
            self.out.tmp.unlink()
        self.linkdir = Path(tempfile.mkdtemp(prefix="evchain-aedat4-"))
        target = self.linkdir / self.path.name  # ends in .aedat4, points at NAME.partial
        try:
            os.symlink(self.out.tmp.resolve(), target)
        except OSError:  # no symbolic links here: write the partial file under a .aedat4 name
            shutil.rmtree(self.linkdir, ignore_errors=True)
            self.linkdir = None
            self.out = AtomicFile.reserve(
                self.path, self.path.with_name(self.path.stem + ".partial.aedat4"))
            target = self.out.tmp
        compression = getattr(dv.CompressionType, COMPRESSIONS[self.params.compression])
        config = dv.io.MonoCameraWriter.Config(self.params.camera, compression)
        config.addEventStream((geometry.width, geometry.height))
        if self.has_imu:
            config.addImuStream()
        try:
            self.writer = dv.io.MonoCameraWriter(str(target), config)
        except RuntimeError as exc:
            raise DataError(f"{self.path}: cannot create the AEDAT 4.0 file: "
                            f"{dv_message(exc)}") from None
        self.geometry = geometry

    def process(self, packet: EventPacket) -> EventPacket:
        if self.geometry is None:
            self.geometry = packet.geometry
        elif packet.geometry.shape != self.geometry.shape:
            raise DataError(f"{self.path}: packet at {packet.t_start} us is "
                            f"{packet.geometry.width}x{packet.geometry.height}, the file is "
                            f"for {self.geometry.width}x{self.geometry.height}")
        if self.out is None:
            self.out = AtomicFile.reserve(self.path)
        imu = packet.series.get(IMU.name)
        if imu is not None:
            if self.writer is not None and not self.has_imu:
                raise DataError(f"{self.path}: the packet at {packet.t_start} us carries IMU "
                                "samples, but the file was opened without an IMU stream (no "
                                "packet before it carried the series imu)")
            self.has_imu = True
            if len(imu):
                self.pending_imu.append(imu)
        if len(packet):
            # dv-processing takes no numpy arrays: one push_back per event. The tuple overload
            # driven by map() is about 3x faster than push_back(t, x, y, p) in a Python loop.
            store = self.dv.EventStore()
            rows = zip(packet.t.tolist(), packet.x.tolist(), packet.y.tolist(),
                       (packet.p > 0).tolist(), strict=True)
            deque(map(store.push_back, rows), maxlen=0)
            self.pending.append(store)
            self.pending_events += len(packet)
        if self.writer is not None or self.pending_events > self.params.buffer_events:
            self._drain()
        return packet

    def _drain(self) -> None:
        if self.writer is None:
            self._open(self.geometry)
        for store in self.pending:
            self.writer.writeEvents(store)
        self.pending, self.pending_events = [], 0
        for imu in self.pending_imu:
            accel, gyro = sensor_axes(imu)
            for t, a, g, c in zip(imu["t"].tolist(), accel.tolist(), gyro.tolist(),
                                  imu["temperature_c"].tolist(), strict=True):
                self.writer.writeImu(self.dv.IMU(t, c, *a, *g, 0.0, 0.0, 0.0))
            self.imu_samples += len(imu)
        self.pending_imu = []

    def flush(self):
        if self.geometry is None:
            self.geometry = self.context.geometry
            if self.geometry is None:
                raise DataError(f"{self.path}: no packets and no sensor geometry; cannot write "
                                "an AEDAT 4.0 file")
        if self.out is None:
            self.out = AtomicFile.reserve(self.path)
        self._drain()
        self.writer = None  # the destructor finishes the file (file data table) and closes it
        self.out.commit()
        self.context.metrics[self.id] = {"path": str(self.path), "imu_samples": self.imu_samples}
        self._remove_link()
        return None

    def _abort(self) -> None:
        """No flush: finish the partial file if one is open, remove any stale ``NAME``."""
        self.writer = None
        self.pending, self.pending_events, self.pending_imu = [], 0, []
        if getattr(self, "out", None) is not None:
            self.out.abort()
        self._remove_link()

    def _remove_link(self) -> None:
        if getattr(self, "linkdir", None) is not None:
            shutil.rmtree(self.linkdir, ignore_errors=True)
            self.linkdir = None

    def close(self):
        self._abort()
