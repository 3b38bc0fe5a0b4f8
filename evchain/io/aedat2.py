"""AEDAT 2.0 (jAER) files: streaming reader and writer, and the ``aedat`` / ``aedat_writer`` stages.

Format (see ``docs/explanation/aedat.md``): ASCII header lines that start with ``#`` and end in
CRLF, the first one ``#!AER-DAT2.0``, the last (as jAER writes it) ``#End Of ASCII Header``;
then 8-byte big-endian records ``(int32 address, int32 timestamp in µs)``. The writer never
starts the records with the byte ``#`` (:func:`first_without_hash`). The address layout depends
on the chip:

* DAVIS240 / DAVIS346 (jAER ``DavisChip``): bit 31 = 0 and bit 10 = 0 for DVS events (bit 31 =
  1 is APS/IMU, bit 10 = 1 an external-input "special" event), y in bits 22-30, x in bits 12-21,
  polarity bit 11 (1 = ON). jAER flips x (``x = W-1-raw``) and its y origin is bottom-left, so in
  evchain's top-left coordinates ``x = W-1-raw_x`` and ``y = H-1-raw_y``.
* DVS128: y in bits 8-14, x in bits 1-7, polarity bit 0, bit 15 a special (sync) event. x flipped
  and bottom-left y as above. Polarity as jAER's code reads it: raw bit 0 == 0 is ON (iniVation's
  written format description says the opposite; jAER is what wrote the files).

Timestamps are unsigned 32-bit µs on disk and unwrapped into int64: a backward step of more than
2**31 µs is a wrap (+2**32), a backward step to a raw time below :data:`RESET_WINDOW_US` and
nearer to 0 than to the time before it is a timestamp reset (time continues from the last
event), backward steps up to ``backstep_tolerance_us`` are clamped; anything else is a
:class:`DataError`.

Everything is vectorised numpy over chunks of records; nothing runs per event in Python.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, Geometry
from evchain.core.series import IMU
from evchain.errors import DataError
from evchain.io.atomic import AtomicFile
from evchain.io.davis_imu import ImuAssembler, is_imu

MAGIC = b"#!AER-DAT"
VERSION_LINE = b"#!AER-DAT2.0"
RECORD_BYTES = 8
WRAP = 1 << 32
HALF = 1 << 31
#: a backward timestamp step landing below this raw time (µs), nearer to 0 than to the time
#: before it, is read as a timestamp reset
RESET_WINDOW_US = 1_000_000
#: DAVIS external-input ("special") event address, written before a first record that would
#: start with the byte ``#`` when no other event of the same time can go first (see
#: :class:`Writer`)
DAVIS_SPECIAL_ADDRESS = 1 << 10
#: the last header line jAER writes (since 2016) and stops reading at, whatever follows
END_OF_HEADER = "End Of ASCII Header"
#: raw DAVIS y rows whose address starts with the byte ``#`` (0x23): ``y_raw >> 2 == 0x23``
HASH_ROWS_RAW = range(0x23 << 2, (0x23 << 2) + 4)

ChipName = Literal["davis240", "davis346", "dvs128"]


@dataclass(frozen=True)
class Chip:
    """One sensor's address layout and size."""

    name: str
    width: int
    height: int
    layout: Literal["davis", "dvs128"]
    jaer_class: str | None = None

    @property
    def geometry(self) -> Geometry:
        return Geometry(self.width, self.height)


CHIPS: dict[str, Chip] = {
    "davis240": Chip("davis240", 240, 180, "davis", "eu.seebetter.ini.chips.davis.DAVIS240C"),
    "davis346": Chip("davis346", 346, 260, "davis", "eu.seebetter.ini.chips.davis.Davis346B"),
    "dvs128": Chip("dvs128", 128, 128, "dvs128", "ch.unizh.ini.jaer.chip.retina.DVS128"),
}

DAVIS_MAX_WIDTH, DAVIS_MAX_HEIGHT = 1 << 10, 1 << 9


def chip_from_class(jaer_class: str) -> Chip | None:
    """The chip a jAER ``AEChip`` class name stands for (case-insensitive), or None."""
    simple = jaer_class.strip().rsplit(".", 1)[-1].lower()
    for key, chip in CHIPS.items():
        if simple.startswith(key):  # DAVIS240C, DAVIS240B, Davis346B, Davis346red, DVS128 ...
            return chip
    return None


def generic_davis(width: int, height: int) -> Chip:
    """The DAVIS bit layout for another sensor size (evchain files of simulated sensors)."""
    if not (0 < width <= DAVIS_MAX_WIDTH and 0 < height <= DAVIS_MAX_HEIGHT):
        raise DataError(f"a {width}x{height} sensor does not fit the DAVIS address layout "
                        f"(at most {DAVIS_MAX_WIDTH}x{DAVIS_MAX_HEIGHT})")
    return Chip(f"davis-{width}x{height}", width, height, "davis")


# ---------------------------------------------------------------------------------------------
# header


@dataclass
class Header:
    """What the header says: its lines (without ``#`` and line ends) and where data starts."""

    path: Path
    lines: list[str]
    data_offset: int
    file_size: int
    chip: Chip | None = None

    @property
    def n_records(self) -> int:
        return (self.file_size - self.data_offset) // RECORD_BYTES


def read_header(path: str | Path) -> Header:
    """Parse the header: lines starting with ``#``, up to and including the line
    ``#End Of ASCII Header`` (as jAER: any case, and here also with spaces around it), else up to
    the first byte that is not ``#``.

    Raises :class:`DataError` for a missing, empty or non-AEDAT-2.0 file and for a truncated
    last record.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file (expected an AEDAT 2.0 file)")
    size = path.stat().st_size
    if size == 0:
        raise DataError(f"{path}: empty file; expected an AEDAT 2.0 header starting with "
                        f"{VERSION_LINE.decode()!r}")
    lines: list[str] = []
    with open(path, "rb") as fh:
        first = fh.readline()
        if not first.startswith(MAGIC):
            raise DataError(f"{path}: not an AEDAT file: byte 0 starts {first[:16]!r}, expected "
                            f"the first line {VERSION_LINE.decode()!r}")
        if not first.startswith(VERSION_LINE):
            version = first.rstrip(b"\r\n")[len(MAGIC):].decode("ascii", "replace")
            raise DataError(f"{path}: AEDAT version {version!r} is not supported; expected "
                            f"{VERSION_LINE.decode()!r} (AEDAT 2.0, jAER)")
        lines.append(first.rstrip(b"\r\n").decode("ascii", "replace")[1:])
        while fh.peek(1)[:1] == b"#":
            lines.append(fh.readline().rstrip(b"\r\n").decode("latin-1")[1:])
            if lines[-1].strip().lower() == END_OF_HEADER.lower():
                break
        offset = fh.tell()
    header = Header(path, lines, offset, size)
    header.chip = _chip_from_lines(lines)
    rest = (size - offset) % RECORD_BYTES
    if rest:
        bad = size - rest
        raise DataError(f"{path}: truncated last record at byte offset {bad} (record "
                        f"{(bad - offset) // RECORD_BYTES}): {rest} bytes, expected "
                        f"{RECORD_BYTES}-byte records (int32 address, int32 timestamp)")
    return header


def _chip_from_lines(lines: list[str]) -> Chip | None:
    for line in lines:
        text = line.strip()
        if text.lower().startswith("aechip:"):
            chip = chip_from_class(text.split(":", 1)[1])
            if chip is not None:
                return chip
        m = re.match(r"evchain-sensor:\s*(\d+)x(\d+)", text)
        if m:
            return generic_davis(int(m.group(1)), int(m.group(2)))
    return None


def header_bytes(chip: Chip, extra: list[str] = ()) -> bytes:
    """The header jAER writes (CRLF line ends), naming the chip's jAER class, ending with
    ``#End Of ASCII Header``."""
    lines = [VERSION_LINE.decode(),
             "# This is a raw AE data file - do not edit",
             "# Data format is int32 address, int32 timestamp (8 bytes total), repeated for each "
             "event",
             "# Timestamps tick is 1 us",
             "# created by evchain"]  # no date or version: same events, same bytes
    if chip.jaer_class:
        lines.append(f"# AEChip: {chip.jaer_class}")
    else:
        lines.append(f"# evchain-sensor: {chip.width}x{chip.height} (jAER DAVIS address layout)")
    lines += [f"# {line}" for line in extra] + [f"#{END_OF_HEADER}"]
    return "".join(line + "\r\n" for line in lines).encode("ascii")


def resolve_chip(header: Header, chip: str | None) -> Chip:
    """The chip named by parameter, else by the header; DataError if neither names one, or if
    both do and differ."""
    if chip is not None:
        if header.chip is not None and header.chip.name != chip:
            named = next((line.strip() for line in header.lines
                          if line.strip().lower().startswith(("aechip:", "evchain-sensor:"))),
                         header.chip.name)
            raise DataError(f"{header.path}: the parameter chip is {chip!r} but the header says "
                            f"'{named}' ({header.chip.name}, {header.chip.width}x"
                            f"{header.chip.height}); remove the parameter to read the header's "
                            "chip")
        return CHIPS[chip]
    if header.chip is None:
        raise DataError(f"{header.path}: the header names no chip (no '# AEChip:' line); set the "
                        f"parameter chip to one of {', '.join(CHIPS)}")
    return header.chip


# ---------------------------------------------------------------------------------------------
# decoding


@dataclass
class DecodeStats:
    events: int = 0
    skipped_non_dvs: int = 0
    wraps: int = 0
    resets: int = 0
    clamped: int = 0
    imu_samples: int = 0
    imu_dropped_records: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class Decoder:
    """Streaming decoder: feed record chunks in file order, get events with unwrapped times."""

    header: Header
    chip: Chip
    non_dvs: Literal["skip", "error"] = "skip"
    backstep_tolerance_us: int = 0
    stats: DecodeStats = field(default_factory=DecodeStats)
    #: DAVIS IMU records: grouped into samples here (None: skipped like other non-DVS records)
    imu: ImuAssembler | None = None
    first_reset_record: int | None = None
    _last_raw: int | None = None
    _last_t: int = 0
    _offset: int = 0
    _imu: list[np.ndarray] = field(default_factory=list)
    _imu_last_t: int | None = None

    def _where(self, record: int) -> str:
        off = self.header.data_offset + RECORD_BYTES * record
        return f"{self.header.path}: record {record} (byte offset {off})"

    def decode(self, raw: np.ndarray, first_record: int):
        """``raw``: big-endian uint32 ``[n, 2]`` (address, timestamp). Returns x, y, t, p.

        One numba pass decodes the usual case; chunks with errors or backward timestamp steps
        go through the numpy path (:meth:`decode_numpy`), which names the culprit.
        """
        from evchain.kernels.aedat2 import decode

        chip = self.chip
        n = len(raw)
        x = np.empty(n, np.uint16)
        y = np.empty(n, np.uint16)
        t = np.empty(n, np.int64)
        p = np.empty(n, np.int8)
        last_t = self._last_t if self._last_raw is not None else np.iinfo(np.int64).min
        words = raw.reshape(-1).view("<u4")
        k, bad, back, skipped = decode(words, 0 if chip.layout == "davis" else 1, chip.width,
                                       chip.height, self._offset, last_t, x, y, t, p)
        imu_rows = None
        if skipped and self.imu is not None and chip.layout == "davis":
            imu_rows = np.flatnonzero(is_imu(raw[:, 0].astype(np.uint32)))
            skipped -= len(imu_rows)
        if bad >= 0 or back >= 0 or (skipped and self.non_dvs == "error"):
            return self.decode_numpy(raw, first_record)
        self.stats.skipped_non_dvs += skipped
        self.stats.events += k
        if imu_rows is not None and len(imu_rows):
            self._take_imu(raw, imu_rows, first_record, None, None, self._offset)
        if k:
            self._last_t = int(t[k - 1])
            self._last_raw = self._last_t - self._offset
        return x[:k], y[:k], t[:k], p[:k]

    def _take_imu(self, raw: np.ndarray, rows: np.ndarray, first_record: int,
                  event_rows: np.ndarray | None, event_offsets: np.ndarray | None,
                  offset_before: int) -> None:
        """Unwrap the IMU records at ``rows`` of the chunk with the offset of the DVS event
        before each (``offset_before`` before the chunk's first event) and group them into
        samples."""
        ts = raw[rows, 1].astype(np.int64)
        off = np.full(len(rows), offset_before, np.int64)
        if event_rows is not None and len(event_rows):
            pos = np.searchsorted(event_rows, rows) - 1
            off = np.where(pos >= 0, event_offsets[np.maximum(pos, 0)], off)
        t = ts + off
        # an IMU record after a wrap but before the next DVS event falls 2^32 us behind
        prev = np.maximum.accumulate(np.concatenate([[self._imu_last_t or t[0]], t]))[:-1]
        t = np.where(t < prev - HALF, t + WRAP, t)
        self._imu_last_t = int(t[-1])
        self._imu.append(self.imu.add(raw[rows, 0].astype(np.uint32), t, first_record + rows))

    def take_imu(self) -> np.ndarray:
        """The IMU samples completed since the last call (:data:`~evchain.core.series.IMU`
        entries, in file order)."""
        out = (np.concatenate(self._imu) if len(self._imu) > 1 else
               self._imu[0] if self._imu else np.zeros(0, IMU.dtype))
        self._imu = []
        if self.imu is not None:
            self.stats.imu_samples = self.imu.samples
            self.stats.imu_dropped_records = self.imu.dropped_records
        return out

    def finish(self) -> None:
        """End of the file: an IMU sample cut off by it is dropped (and counted)."""
        if self.imu is not None:
            self.imu.finish()
            self.stats.imu_dropped_records = self.imu.dropped_records

    def decode_numpy(self, raw: np.ndarray, first_record: int):
        """The same as :meth:`decode` in numpy, with the unwrapping of backward steps."""
        addr = raw[:, 0].astype(np.uint32)
        ts = raw[:, 1].astype(np.uint32)
        chip = self.chip
        offset_before = self._offset
        imu_rows = None
        if chip.layout == "davis":
            special = addr & np.uint32(0x80000400)
            keep = None
            if special.any():
                keep = special == 0
                if self.imu is not None:
                    imu_rows = np.flatnonzero(is_imu(addr))
        else:
            high = addr >> np.uint32(15)
            keep = None
            if high.any():
                if (high > 1).any():
                    i = int(np.argmax(high > 1))
                    raise DataError(f"{self._where(first_record + i)}: address 0x{addr[i]:08x} "
                                    "does not fit the DVS128 layout (16-bit addresses); is this a "
                                    "DAVIS file? set chip")
                keep = high == 0
        if keep is not None:
            n_imu = 0 if imu_rows is None else len(imu_rows)
            n_skip = len(keep) - int(np.count_nonzero(keep)) - n_imu
            if n_skip and self.non_dvs == "error":
                other = ~keep
                if n_imu:
                    other[imu_rows] = False
                i = int(np.argmax(other))
                raise DataError(f"{self._where(first_record + i)}: non-DVS record (address "
                                f"0x{addr[i]:08x}, APS/IMU/special) and non_dvs='error'")
            self.stats.skipped_non_dvs += n_skip
            index = np.flatnonzero(keep)
            addr = addr[index]
            ts = ts[index]
        else:
            index = None
        if chip.layout == "davis":
            xr = (addr >> np.uint32(12)) & np.uint32(0x3FF)
            yr = addr >> np.uint32(22)
            pr = (addr >> np.uint32(11)) & np.uint32(1)
        else:
            xr = (addr >> np.uint32(1)) & np.uint32(0x7F)
            yr = (addr >> np.uint32(8)) & np.uint32(0x7F)
            pr = (addr & np.uint32(1)) ^ np.uint32(1)  # jAER: raw 0 is ON
        if len(addr) and (xr.max() >= chip.width or yr.max() >= chip.height):
            i = int(np.argmax((xr >= chip.width) | (yr >= chip.height)))
            rec = first_record + (i if index is None else int(index[i]))
            raise DataError(f"{self._where(rec)}: address 0x{addr[i]:08x} decodes to raw "
                            f"(x={xr[i]}, y={yr[i]}), outside the {chip.width}x{chip.height} "
                            f"sensor of chip {chip.name}; expected x < {chip.width}, "
                            f"y < {chip.height} (wrong chip?)")
        x = (np.uint32(chip.width - 1) - xr).astype(np.uint16)
        y = (np.uint32(chip.height - 1) - yr).astype(np.uint16)
        p = (pr.astype(np.int8) << np.int8(1)) - np.int8(1)
        t = self._unwrap(ts, first_record, index)
        self.stats.events += len(t)
        if imu_rows is not None and len(imu_rows):
            self._take_imu(raw, imu_rows, first_record, index, t - ts.astype(np.int64),
                           offset_before)
        return x, y, t, p

    def _unwrap(self, ts: np.ndarray, first_record: int, index) -> np.ndarray:
        t = ts.astype(np.int64)
        if len(t) == 0:
            return t
        prev = int(t[0]) if self._last_raw is None else self._last_raw
        self._last_raw = int(t[-1])
        d0 = int(t[0]) - prev
        if d0 >= 0 and (len(t) == 1 or bool(np.all(t[1:] >= t[:-1]))):
            t += self._offset  # the common case: no backward step in this chunk
        else:
            d = np.empty_like(t)
            d[0] = d0
            np.subtract(t[1:], t[:-1], out=d[1:])
            wrap = d < -HALF
            # a reset restarts the counter near 0: below the window, and nearer to 0 than to
            # the time before (a step back from 500 ms to 495 ms is no reset)
            reset = ((d < -self.backstep_tolerance_us) & ~wrap & (t < RESET_WINDOW_US)
                     & (t < -d))
            if self.first_reset_record is None and reset.any():
                i = int(np.argmax(reset))
                self.first_reset_record = first_record + (i if index is None else int(index[i]))
            inc = np.where(wrap, WRAP, 0) + np.where(reset, -d, 0)
            self.stats.wraps += int(np.count_nonzero(wrap))
            self.stats.resets += int(np.count_nonzero(reset))
            offsets = np.cumsum(inc) + self._offset
            t += offsets
            self._offset = int(offsets[-1])
            step = np.empty_like(t)
            step[0] = t[0] - self._last_t
            np.subtract(t[1:], t[:-1], out=step[1:])
            if self.stats.events == 0:
                step[0] = 0
            if step.min() < 0:
                if step.min() < -self.backstep_tolerance_us:
                    i = int(np.argmax(step < -self.backstep_tolerance_us))
                    rec = first_record + (i if index is None else int(index[i]))
                    before = int(ts[i - 1]) if i else "the previous record's"
                    raise DataError(
                        f"{self._where(rec)}: timestamp goes back from {before} to {int(ts[i])} "
                        f"us (raw), by {-int(step[i])} us: not a 32-bit wrap (a backward step "
                        f"of more than 2^31 us), not a timestamp reset (a restart below "
                        f"{RESET_WINDOW_US} us, nearer to 0 than to the time before); raise "
                        "backstep_tolerance_us to clamp such steps")
                self.stats.clamped += int(np.count_nonzero(step < 0))
                t[0] = max(int(t[0]), self._last_t)
                np.maximum.accumulate(t, out=t)
        self._last_t = int(t[-1])
        return t


def iter_raw(header: Header, chunk_records: int, fh: BinaryIO | None = None
             ) -> Iterator[tuple[np.ndarray, int]]:
    """Yield ``(records [n, 2] big-endian uint32, index of the first record)`` chunk by chunk."""
    own = fh is None
    if own:
        fh = open(header.path, "rb")
    try:
        fh.seek(header.data_offset)
        first = 0
        while True:
            buf = fh.read(chunk_records * RECORD_BYTES)
            if not buf:
                break
            if len(buf) % RECORD_BYTES:
                off = header.data_offset + (first + len(buf) // RECORD_BYTES) * RECORD_BYTES
                raise DataError(f"{header.path}: truncated last record at byte offset {off}; "
                                f"expected {RECORD_BYTES}-byte records")
            raw = np.frombuffer(buf, dtype=">u4").reshape(-1, 2)
            yield raw, first
            first += len(raw)
    finally:
        if own:
            fh.close()


def iter_events(path: str | Path, chip: ChipName | None = None, chunk_records: int = 1 << 20,
                non_dvs: Literal["skip", "error"] = "skip", backstep_tolerance_us: int = 0,
                stats: DecodeStats | None = None, header: Header | None = None):
    """Yield ``(x, y, t, p)`` chunks of a file's DVS events in evchain coordinates."""
    header = header or read_header(path)
    dec = Decoder(header, resolve_chip(header, chip), non_dvs, backstep_tolerance_us)
    if stats is not None:
        dec.stats = stats
    for raw, first in iter_raw(header, chunk_records):
        yield dec.decode(raw, first)


def read_aedat2(path: str | Path, chip: ChipName | None = None, chunk_records: int = 1 << 20,
                non_dvs: Literal["skip", "error"] = "skip", backstep_tolerance_us: int = 0,
                stats: DecodeStats | None = None) -> EventPacket:
    """Read a whole file into one :class:`EventPacket` (slice ``[t0, t_last + 1)``)."""
    header = read_header(path)
    geometry = resolve_chip(header, chip).geometry
    parts = list(iter_events(path, chip, chunk_records, non_dvs, backstep_tolerance_us, stats,
                             header))
    if not parts:
        return EventPacket.empty(geometry, 0, 0)
    x, y, t, p = (np.concatenate(cols) for cols in zip(*parts, strict=True))
    t0 = int(t[0]) if len(t) else 0
    t1 = int(t[-1]) + 1 if len(t) else 0
    return EventPacket(geometry=geometry, t_start=t0, t_end=t1, x=x, y=y, t=t, p=p)


# ---------------------------------------------------------------------------------------------
# encoding


def encode_records(chip: Chip, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray
                   ) -> np.ndarray:
    """Records ``[n, 2]`` as big-endian uint32 for events in evchain coordinates (timestamps
    modulo 2**32; the reader unwraps them)."""
    n = len(x)
    if n and (int(x.max()) >= chip.width or int(y.max()) >= chip.height):
        raise DataError(f"event outside the {chip.width}x{chip.height} sensor of chip "
                        f"{chip.name}: cannot write it")
    xr = np.uint32(chip.width - 1) - x.astype(np.uint32)
    yr = np.uint32(chip.height - 1) - y.astype(np.uint32)
    on = (p > 0).astype(np.uint32)
    if chip.layout == "davis":
        addr = (yr << np.uint32(22)) | (xr << np.uint32(12)) | (on << np.uint32(11))
    else:
        addr = (yr << np.uint32(8)) | (xr << np.uint32(1)) | (on ^ np.uint32(1))
    out = np.empty((n, 2), dtype=">u4")
    out[:, 0] = addr
    out[:, 1] = t.astype(np.uint64) & np.uint64(0xFFFFFFFF) if n else 0
    return out


def first_without_hash(chip: Chip, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray
                       ) -> tuple[tuple[np.ndarray, ...], bool]:
    """The file's first events, arranged so that the data does not start with the byte ``#``.

    Readers that end the header at the first byte that is not ``#`` (tonic, many scripts, and
    jAER before it wrote ``#End Of ASCII Header``) swallow a first record starting with ``#``
    (a DAVIS event in raw rows 140..143) as a header line. If another event of the same time
    starts otherwise, it goes first (events of equal time have no order in the format). Returns
    the columns and whether no such event exists: then the writer puts a DAVIS special event
    first, which jAER marks special and evchain skips, but which readers that ignore the
    special bit take for an OFF event at raw address 0.
    """
    if chip.layout != "davis" or not len(t) or chip.height - 1 - int(y[0]) not in HASH_ROWS_RAW:
        return (x, y, t, p), False
    k = int(np.searchsorted(t, t[0], side="right"))
    rows = chip.height - 1 - y[:k].astype(np.int64)
    free = np.flatnonzero((rows < HASH_ROWS_RAW.start) | (rows >= HASH_ROWS_RAW.stop))
    if not len(free):
        return (x, y, t, p), True
    j = int(free[0])
    return tuple(np.concatenate([c[j:j + 1], c[:j], c[j + 1:]]) for c in (x, y, t, p)), False


class Writer:
    """Streaming AEDAT 2.0 writer onto a binary file object (header written on creation)."""

    def __init__(self, fh, chip: Chip, extra_header: list[str] = ()):
        self.fh, self.chip = fh, chip
        self.name = str(getattr(fh, "path", None) or getattr(fh, "name", "AEDAT output"))
        fh.write(header_bytes(chip, list(extra_header)))
        self.events = 0
        self.specials = 0
        self._last_t: int | None = None

    def write(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
        from evchain.kernels.aedat2 import encode

        if len(t) == 0:
            return
        t = np.asarray(t, np.int64)
        prev = int(t[0]) if self._last_t is None else self._last_t
        chip = self.chip
        lead = False
        if self.events == 0:
            (x, y, t, p), lead = first_without_hash(chip, x, y, t, p)
        words = np.empty(2 * len(t), "<u4")
        bad, gap = encode(x, y, t, p, 0 if chip.layout == "davis" else 1, chip.width,
                          chip.height, prev, words)
        if bad >= 0:
            raise DataError(f"{self.name}: event {bad} at ({x[bad]}, {y[bad]}) is outside the "
                            f"{chip.width}x{chip.height} sensor of chip {chip.name}: cannot "
                            "write it")
        if gap >= 0:
            before = int(t[gap - 1]) if gap else prev
            raise DataError(f"{self.name}: event {gap} at {int(t[gap])} us follows {before} us: a "
                            "gap of 2^31 us or more cannot be written to AEDAT 2.0 (32-bit "
                            "timestamps)")
        if lead:  # the special record, see first_without_hash
            self.fh.write(np.array([[DAVIS_SPECIAL_ADDRESS, int(t[0]) & 0xFFFFFFFF]],
                                   ">u4").tobytes())
            self.specials += 1
        self.fh.write(words)
        self.events += len(t)
        self._last_t = int(t[-1])


def write_aedat2(path: str | Path, events: EventPacket, chip: ChipName | None = None) -> Path:
    """Write ``events`` to ``path`` atomically (``path.partial`` until complete)."""
    c = chip_for(events.geometry, chip)
    with AtomicFile(path) as out:
        Writer(out, c).write(events.x, events.y, events.t, events.p)
    return Path(path)


def chip_for(geometry: Geometry | None, chip: str | None) -> Chip:
    """The chip to write: by name, else the known chip of this size, else generic DAVIS."""
    if chip is not None:
        c = CHIPS[chip]
        if geometry is not None and (geometry.width > c.width or geometry.height > c.height):
            raise DataError(f"a {geometry.width}x{geometry.height} sensor does not fit chip "
                            f"{chip} ({c.width}x{c.height})")
        return c
    if geometry is None:
        raise DataError("no sensor geometry known: set the parameter chip")
    for c in CHIPS.values():
        if (c.width, c.height) == (geometry.width, geometry.height):
            return c
    return generic_davis(geometry.width, geometry.height)


# ---------------------------------------------------------------------------------------------
# filters


class AedatSource(Filter):
    """Read DVS events (and DAVIS IMU samples) from an AEDAT 2.0 (jAER) file in time slices.

    The chip (address layout and size) comes from the parameter ``chip`` or from the header's
    ``# AEChip:`` line. DAVIS IMU samples become the series ``imu`` (camera axes, g and deg/s;
    :mod:`evchain.io.davis_imu`; from the file's first sample on, none without IMU records),
    with the full scales from jAER's preferences in the header
    or, where it says none, from ``gyro_full_scale_dps`` and ``accel_full_scale_g``. Other
    non-DVS records (APS, special events) are skipped and counted in ``metrics[<id>]``;
    32-bit timestamp wraps and resets are unwrapped into int64 µs.
    """

    name = "aedat"
    consumes = None
    produces = EventPacket
    adds_series = (IMU,)
    input_paths = ("path",)

    class Params(FilterParams):
        path: str = Field(description="AEDAT 2.0 file to read")
        chip: ChipName | None = Field(None, description="address layout; default: the header's "
                                                        "'# AEChip:' line")
        packet_us: int = Field(10_000, ge=1, description="duration of one output slice in µs")
        chunk_records: int = Field(1 << 20, ge=1, le=1 << 26,
                                   description="records read from disk at a time")
        non_dvs: Literal["skip", "error"] = Field(
            "skip", description="what to do with APS/special records (and IMU records when "
                                "imu is false)")
        backstep_tolerance_us: int = Field(
            0, ge=0, description="backward timestamp steps up to this are clamped, not errors")
        imu: bool = Field(True, description="read DAVIS IMU samples into the series imu; "
                                            "false: skip them like other non-DVS records")
        gyro_full_scale_dps: Literal[250, 500, 1000, 2000] | None = Field(
            None, description="gyro full scale, deg/s, for files whose header does not say it "
                              "(jAER's ImuGyroScale); must agree with the header if it does")
        accel_full_scale_g: Literal[2, 4, 8, 16] | None = Field(
            None, description="accelerometer full scale, g, for files whose header does not "
                              "say it (jAER's ImuAccelScale); must agree with the header")

    @classmethod
    def series_added(cls, params):
        """``imu`` unless ``imu`` is false."""
        return (IMU,) if params.imu else ()

    def setup(self, params, context) -> None:
        from evchain.io.davis_imu import resolve_scales, scales_from_header

        super().setup(params, context)
        self.header = read_header(params.path)
        self.chip = resolve_chip(self.header, params.chip)
        try:
            found = scales_from_header(self.header.lines)
        except DataError as exc:
            raise DataError(f"{self.header.path}: {exc}") from None
        self.imu_scales = resolve_scales(found, params.gyro_full_scale_dps,
                                         params.accel_full_scale_g, str(self.header.path))
        context.geometry = self.chip.geometry

    def reset(self) -> None:
        self.stats = DecodeStats()

    def time_span_us(self) -> tuple[int, int] | None:
        h = self.header
        if h.n_records == 0:
            return None
        with open(h.path, "rb") as fh:
            fh.seek(h.data_offset)
            first = np.frombuffer(fh.read(8), ">u4")
            fh.seek(h.data_offset + (h.n_records - 1) * RECORD_BYTES)
            last = np.frombuffer(fh.read(8), ">u4")
        t0, t1 = int(first[1]), int(last[1])
        if t1 < t0:
            t1 += WRAP
        return t0, t1 + 1

    def packets(self) -> Iterator[EventPacket]:
        self.stats = DecodeStats()
        prm = self.params
        imu = None
        if prm.imu and self.chip.layout == "davis":
            imu = ImuAssembler(self.imu_scales, str(self.header.path))
        dec = Decoder(self.header, self.chip, prm.non_dvs, prm.backstep_tolerance_us, self.stats,
                      imu)
        self._imu_pending = np.zeros(0, IMU.dtype)
        self._imu_late = 0
        self._imu_seen = False
        for packet in self._packets(dec):
            yield self._with_imu(packet) if prm.imu else packet
        if self.stats.resets:
            self.context.warn(
                f"{self.id}: {self.header.path}: the timestamps were reset {self.stats.resets} "
                f"time(s) (first at record {dec.first_reset_record}); time continues from the "
                "event before each reset, the pause at a reset is unknown and counted as 0")
        if imu is not None and imu.dropped_records:
            self.context.warn(
                f"{self.id}: {self.header.path}: {imu.dropped_records} IMU record(s) formed no "
                f"complete sample (7 records of types 0..6; first at record "
                f"{imu.first_dropped}) and were dropped")
        metrics = {"file": str(self.header.path), "chip": self.chip.name,
                   **self.stats.as_dict()}
        if prm.imu:
            metrics["imu_late"] = self._imu_late
            metrics["imu_full_scale"] = {"gyro_dps": self.imu_scales.gyro_dps,
                                         "accel_g": self.imu_scales.accel_g,
                                         "from": self.imu_scales.source}
        self.context.metrics[self.id] = metrics

    def _take_imu(self, dec: Decoder) -> None:
        got = dec.take_imu()
        if len(got):   # kept in time order (stable), so that each slice's are found by bisection
            pend = np.concatenate([self._imu_pending, got])
            self._imu_pending = pend[np.argsort(pend["t"], kind="stable")]

    def _with_imu(self, packet: EventPacket) -> EventPacket:
        """``packet`` with the IMU samples of its slice (in time order) as the series ``imu``,
        from the first sample of the file on (a file without IMU records gives no series);
        samples that arrive after their slice was emitted (written out of time order) are
        counted in ``imu_late`` and dropped."""
        pend = self._imu_pending
        i0, i1 = np.searchsorted(pend["t"], [packet.t_start, packet.t_end], side="left")
        self._imu_late += int(i0)
        mine = pend[i0:max(i0, i1)]
        self._imu_pending = pend[max(i0, i1):]
        self._imu_seen = self._imu_seen or len(pend) > 0
        return packet.with_series(IMU.name, mine) if self._imu_seen else packet

    def _packets(self, dec: Decoder) -> Iterator[EventPacket]:
        prm = self.params
        geom = self.chip.geometry
        P = prm.packet_us
        pending: list[tuple[np.ndarray, ...]] = []
        start = None  # start of the next slice to emit
        t0 = None
        for raw, first in iter_raw(self.header, prm.chunk_records):
            x, y, t, p = dec.decode(raw, first)
            self._take_imu(dec)
            if len(t) == 0:
                continue
            if t0 is None:
                t0 = start = int(t[0])
                if len(self._imu_pending):  # IMU samples before the first event
                    t0 = start = min(t0, int(self._imu_pending["t"][0]))
            last_t = int(t[-1])
            cut = t0 + (last_t - t0) // P * P  # start of the slice holding the last event
            if cut <= start:
                pending.append((x, y, t, p))
                continue
            if sum(len(c[2]) for c in pending):  # close the pending slice without copying all
                i = int(np.searchsorted(t, start + P, side="left"))
                px, py, pt, pp = (np.concatenate(c) for c in zip(*pending, (x[:i], y[:i], t[:i],
                                                                          p[:i]), strict=True))
                yield EventPacket(geometry=geom, t_start=start, t_end=start + P, x=px, y=py,
                                  t=pt, p=pp)
                start += P
                x, y, t, p = x[i:], y[i:], t[i:], p[i:]
            done = int(np.searchsorted(t, cut, side="left"))
            yield from self._slices(geom, x[:done], y[:done], t[:done], p[:done], start, cut, t0)
            pending = [(x[done:], y[done:], t[done:], p[done:])]
            start = cut
        dec.finish()
        if t0 is not None:
            x, y, t, p = (np.concatenate(c) for c in zip(*pending, strict=True))
            end = int(t[-1]) + 1 if len(t) else start + 1
            if len(self._imu_pending):  # IMU samples after the last event
                end = max(end, int(self._imu_pending["t"][-1]) + 1)
            yield EventPacket(geometry=geom, t_start=start, t_end=end, x=x, y=y, t=t, p=p)

    def _slices(self, geom, x, y, t, p, start: int, stop: int, t0: int):
        """Packets for ``[start, stop)`` cut every ``packet_us`` from ``t0``; runs of empty
        slices are merged into one empty packet."""
        P = self.params.packet_us
        k0 = (start - t0) // P
        k1 = (stop - t0) // P
        edges = t0 + P * np.arange(k0, k1 + 1, dtype=np.int64)
        idx = np.searchsorted(t, edges, side="left")
        a = 0
        while a < len(edges) - 1:
            i0, i1 = int(idx[a]), int(idx[a + 1])
            b = a + 1
            if i0 == i1:  # merge a run of empty slices
                while b < len(edges) - 1 and int(idx[b + 1]) == i0:
                    b += 1
            yield EventPacket(geometry=geom, t_start=int(edges[a]), t_end=int(edges[b]),
                              x=x[i0:i1], y=y[i0:i1], t=t[i0:i1], p=p[i0:i1])
            a = b


class AedatWriter(Filter):
    """Write the events passing through to an AEDAT 2.0 (jAER) file; passes packets on.

    The file is written as ``PATH.partial`` and renamed to ``PATH`` only at the end of a
    successful run. ``chip`` defaults to the chip of the sensor's size; other sizes use the DAVIS
    address layout with an ``# evchain-sensor: WxH`` header line (evchain reads it back; jAER
    would need a matching chip class).
    """

    name = "aedat_writer"
    consumes = EventPacket
    produces = None
    output_paths = ("path",)

    class Params(FilterParams):
        path: str = Field("events.aedat", description="output file, relative to the run's "
                                                      "output folder")
        chip: ChipName | None = Field(None, description="address layout; default: from the "
                                                        "sensor size")

    _out: AtomicFile | None = None
    _writer: Writer | None = None

    @classmethod
    def check_sensor(cls, params: Params, width: int, height: int) -> str | None:
        """AEDAT 2.0 addresses (DAVIS layout) hold at most 1024x512 pixels; a named chip at
        most its own size."""
        if params.chip is not None:
            c = CHIPS[params.chip]
            if width > c.width or height > c.height:
                return (f"chip: a {width}x{height} sensor does not fit chip {c.name} "
                        f"({c.width}x{c.height})")
            return None
        if width > DAVIS_MAX_WIDTH or height > DAVIS_MAX_HEIGHT:
            return (f"a {width}x{height} sensor does not fit AEDAT 2.0, whose addresses hold at "
                    f"most {DAVIS_MAX_WIDTH}x{DAVIS_MAX_HEIGHT} pixels; write the events with "
                    "aedat4_writer (AEDAT 4, plugin evchain-dv) or hdf5_writer instead")
        return None

    def reset(self) -> None:
        if self._out is not None:
            self._out.abort()
        self._out = None
        self._writer = None
        self._committed = False

    def _open(self, geometry: Geometry | None) -> Writer:
        if self._writer is None:
            chip = chip_for(geometry, self.params.chip)
            self._out = AtomicFile(self.context.output_path(self.params.path))
            self._writer = Writer(self._out, chip)
        return self._writer

    def process(self, packet: EventPacket) -> EventPacket:
        self._open(packet.geometry).write(packet.x, packet.y, packet.t, packet.p)
        return packet

    def flush(self) -> None:
        w = self._open(self.context.geometry)
        self._out.commit()
        self._committed = True
        self.context.metrics[self.id] = {"path": str(self._out.path), "chip": w.chip.name,
                                         "events": w.events, "special_records": w.specials}
        return None

    def close(self) -> None:
        if self._out is not None and not self._committed:
            self._out.abort()


def read_imu(path: str | Path, chip: ChipName | None = None,
             gyro_full_scale_dps: int | None = None, accel_full_scale_g: int | None = None,
             chunk_records: int = 1 << 20) -> np.ndarray:
    """Every complete IMU sample of a DAVIS file as :data:`~evchain.core.series.IMU` entries
    (camera axes, g and deg/s; full scales from the header, else the arguments)."""
    from evchain.io.davis_imu import resolve_scales, scales_from_header

    header = read_header(path)
    c = resolve_chip(header, chip)
    scales = resolve_scales(scales_from_header(header.lines), gyro_full_scale_dps,
                            accel_full_scale_g, str(header.path))
    if c.layout != "davis":
        return np.zeros(0, IMU.dtype)
    dec = Decoder(header, c, imu=ImuAssembler(scales, str(header.path)))
    parts = []
    for raw, first in iter_raw(header, chunk_records):
        dec.decode(raw, first)
        parts.append(dec.take_imu())
    dec.finish()
    return np.concatenate(parts) if parts else np.zeros(0, IMU.dtype)
