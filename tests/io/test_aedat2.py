"""AEDAT 2.0 reader, writer and their stages: round trips, jAER conventions, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.errors import ConfigError, DataError
from evchain.io.aedat2 import (
    CHIPS,
    AedatSource,
    AedatWriter,
    DecodeStats,
    header_bytes,
    read_aedat2,
    read_header,
    write_aedat2,
)
from evchain.testing.contract import check_filter, check_source, recut
from evchain.testing.synthetic import random_events

REPO = Path(__file__).resolve().parents[2]
DVSFLOW = REPO / ".." / "shared" / "data" / "dvsflow16"
SQUARE = DVSFLOW / "TranslatingSquare.aedat"
SHIPPED = REPO / "tests" / "data" / "moving_edge_davis240.aedat"


def raw_file(path: Path, addr, ts, chip: str | None = "davis240", header: bytes | None = None):
    """A file with hand-built records (address, timestamp as unsigned 32-bit)."""
    rec = np.empty((len(addr), 2), ">u4")
    rec[:, 0] = np.asarray(addr, np.uint64).astype(np.uint32)
    rec[:, 1] = np.asarray(ts, np.uint64).astype(np.uint32)
    if header is None:
        header = header_bytes(CHIPS[chip]) if chip else b"#!AER-DAT2.0\r\n# no chip here\r\n"
    path.write_bytes(header + rec.tobytes())
    return path


def davis(x_raw, y_raw, on):
    return (np.asarray(y_raw, np.uint32) << 22) | (np.asarray(x_raw, np.uint32) << 12) | (
        np.asarray(on, np.uint32) << 11)


def same(a: EventPacket, b: EventPacket) -> bool:
    return all(np.array_equal(getattr(a, c), getattr(b, c)) for c in EventPacket.columns)


# --- round trips and conventions -------------------------------------------------------------

@pytest.mark.parametrize("chip", sorted(CHIPS))
def test_round_trip_every_chip(tmp_path, chip):
    g = CHIPS[chip].geometry
    ev = random_events(5000, g, 0, 3_000_000, seed=1)
    ev = ev.replace(x=np.concatenate([[0, g.width - 1], ev.x[2:]]).astype(np.uint16),
                    y=np.concatenate([[0, g.height - 1], ev.y[2:]]).astype(np.uint16))
    path = write_aedat2(tmp_path / "a.aedat", ev, chip=chip)
    header = read_header(path)
    assert header.chip.name == chip  # the chip is named in the header and found again
    back = read_aedat2(path)
    assert back.geometry == g
    assert same(ev, back)
    back.validate()


def test_davis_coordinates_follow_jaer(tmp_path):
    # jAER: x = W-1-raw_x, y origin bottom-left, bit 11 = ON. evchain is top-left.
    path = raw_file(tmp_path / "d.aedat", davis([0, 239, 5], [0, 179, 7], [1, 0, 1]), [1, 2, 3])
    ev = read_aedat2(path)
    assert ev.x.tolist() == [239, 0, 234]
    assert ev.y.tolist() == [179, 0, 172]
    assert ev.p.tolist() == [1, -1, 1]


def test_dvs128_polarity_as_jaer_code_reads_it(tmp_path):
    # y bits 8-14, x bits 1-7, raw polarity bit 0 == 0 is ON (jAER code; iniVation's spec differs)
    addr = [(3 << 8) | (5 << 1) | 0, (3 << 8) | (5 << 1) | 1]
    ev = read_aedat2(raw_file(tmp_path / "d.aedat", addr, [10, 11], chip="dvs128"))
    assert ev.p.tolist() == [1, -1]
    assert ev.x.tolist() == [127 - 5] * 2 and ev.y.tolist() == [127 - 3] * 2


def test_non_dvs_records_are_skipped_and_counted(tmp_path):
    addr = [davis(1, 1, 1), 0x80000000 | 5, davis(2, 2, 0), 0x80000C00, 1 << 10, davis(3, 3, 1)]
    stats = DecodeStats()
    ev = read_aedat2(raw_file(tmp_path / "d.aedat", np.array(addr), [1, 2, 3, 4, 5, 6]),
                     stats=stats)
    assert ev.t.tolist() == [1, 3, 6]
    assert stats.skipped_non_dvs == 3
    with pytest.raises(DataError, match=r"d\.aedat: record 1 .*non-DVS"):
        read_aedat2(tmp_path / "d.aedat", non_dvs="error")


@pytest.mark.skipif(not SQUARE.exists(), reason="shared dvsflow16 data not present")
def test_translating_square_reads_and_round_trips(tmp_path):
    ev = read_aedat2(SQUARE, chip="davis240")
    assert len(ev) == 16_000
    assert ev.geometry == Geometry(240, 180)
    assert ev.x.max() < 240 and ev.y.max() < 180
    assert np.count_nonzero(ev.p > 0) == 8000  # leading and trailing edges, opposite polarity
    ev.validate()
    out = write_aedat2(tmp_path / "sq.aedat", ev, chip="davis240")
    again = read_aedat2(out)
    assert same(ev, again)
    # the records themselves are byte-identical to jAER's
    src, dst = read_header(SQUARE), read_header(out)
    assert SQUARE.read_bytes()[src.data_offset:] == out.read_bytes()[dst.data_offset:]


@pytest.mark.skipif(not SQUARE.exists(), reason="shared dvsflow16 data not present")
@pytest.mark.parametrize("name,count", [("RotatingBar", 45_000), ("TranslatingBarX", 10_000),
                                        ("TranslatingBarY", 10_000)])
def test_other_dvsflow16_files(name, count):
    stats = DecodeStats()
    ev = read_aedat2(DVSFLOW / f"{name}.aedat", chip="davis240", stats=stats)
    assert len(ev) == count and stats.skipped_non_dvs == 0
    ev.validate()
    if name == "RotatingBar":  # rotates about jAER (119, 89): evchain (119, 179 - 89)
        assert abs((int(ev.x.min()) + int(ev.x.max())) / 2 - 119) <= 1
        assert abs((int(ev.y.min()) + int(ev.y.max())) / 2 - 90) <= 1


def test_lf_only_header_is_accepted(tmp_path):
    header = b"#!AER-DAT2.0\n# AEChip: ch.unizh.ini.jaer.chip.retina.DVS128\n"
    path = raw_file(tmp_path / "lf.aedat", [(3 << 8) | (5 << 1)], [42], header=header)
    ev = read_aedat2(path)
    assert ev.geometry == Geometry(128, 128) and ev.t.tolist() == [42]


def test_header_lines_crlf_and_stop_at_first_non_hash_byte(tmp_path):
    path = raw_file(tmp_path / "h.aedat", davis([1], [1], [1]), [5])
    data = path.read_bytes()
    header = read_header(path)
    head = data[:header.data_offset]
    assert head.startswith(b"#!AER-DAT2.0\r\n")
    assert all(line.startswith(b"#") for line in head.split(b"\r\n")[:-1])
    assert b"# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n" in head
    assert head.count(b"\n") == head.count(b"\r\n")
    assert header.data_offset == len(header_bytes(CHIPS["davis240"]))
    assert header.n_records == 1


def jaer_data_offset(data: bytes) -> int:
    """Where jAER's AEFileInputStream starts reading records (its readHeaderLine, from its
    description): line by line, a line equal to 'End Of ASCII Header' after its first byte (any
    case) ends the header after itself, a line not starting with '#' ends it before itself;
    each header line counts its length plus the '#' and CRLF."""
    offset = 0
    while True:
        end = data.find(b"\n", offset)
        if end < 0:  # a last line without line end: no data at all
            return len(data) if data[offset:offset + 1] == b"#" else offset
        line = data[offset + 1:end].rstrip(b"\r")
        if line.decode("latin-1").lower() == "end of ascii header":
            return offset + len(line) + 3
        if data[offset:offset + 1] != b"#":
            return offset
        offset += len(line) + 3


def hash_first(chip: str, y_raw: int, n_same: int, seed: int = 0) -> EventPacket:
    """Events whose first one lies in raw row ``y_raw`` (140..143: its record starts with '#'),
    with ``n_same`` events at the first time; the others of that time lie in other rows."""
    g = CHIPS[chip].geometry
    ev = random_events(300, g, 100, 50_000, seed=seed)
    y = ev.y.copy()
    y[0] = g.height - 1 - y_raw
    y[1:n_same] = g.height - 1 - 20
    t = ev.t.copy()
    t[:n_same] = 100
    t[n_same:] = np.maximum(t[n_same:], 101)
    return ev.replace(y=y, t=np.sort(t), t_start=100)


def test_header_ends_with_the_line_jaer_writes_and_stops_at(tmp_path):
    head = header_bytes(CHIPS["davis240"])
    assert head.endswith(b"\r\n#End Of ASCII Header\r\n")
    hash_rec = davis([235], [141], [1])  # first byte 0x23 '#'
    path = raw_file(tmp_path / "a.aedat", hash_rec, [7])
    assert read_header(path).data_offset == len(head) == jaer_data_offset(path.read_bytes())
    ev = read_aedat2(path)
    assert (ev.x.tolist(), ev.y.tolist(), ev.p.tolist()) == ([4], [38], [1])
    # jAER stops at the marker in any case; evchain also with spaces around it
    for line in (b"#end of ascii header\r\n", b"# End Of ASCII Header \r\n"):
        path = raw_file(tmp_path / "b.aedat", hash_rec, [7],
                        header=b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis."
                        b"DAVIS240C\r\n" + line)
        assert read_header(path).n_records == 1
    # without the marker every reader takes the '#' record for a header line
    plain = raw_file(tmp_path / "c.aedat", hash_rec, [7], header=b"#!AER-DAT2.0\r\n# AEChip: "
                     b"eu.seebetter.ini.chips.davis.DAVIS240C\r\n")
    assert read_header(plain).n_records == 0
    assert jaer_data_offset(plain.read_bytes()) == plain.stat().st_size


@pytest.mark.parametrize("chip", ["davis240", "davis346"])
@pytest.mark.parametrize("y_raw", [140, 141, 142, 143])
def test_first_record_never_starts_with_hash(tmp_path, chip, y_raw):
    """Another event of the first time goes first: no extra record, the data starts with
    another byte, and jAER's rule, evchain and tonic all read exactly the written events (the
    first two events of equal time swapped)."""
    ev = hash_first(chip, y_raw, n_same=3, seed=y_raw)
    path = write_aedat2(tmp_path / "x.aedat", ev)
    header = read_header(path)
    data = path.read_bytes()
    assert data[header.data_offset] != ord("#")
    assert header.n_records == len(ev)
    assert jaer_data_offset(data) == header.data_offset
    stats = DecodeStats()
    back = read_aedat2(path, stats=stats)
    order = np.r_[1, 0, 2:len(ev)]
    assert same(back, ev.select(order)) and stats.skipped_non_dvs == 0
    tonic_io = pytest.importorskip("tonic.io")
    version, start, *_ = tonic_io.read_aedat_header_from_file(str(path))
    assert (version, start) == (2.0, header.data_offset)
    raw = tonic_io.get_aer_events_from_file(str(path), version, start)
    assert len(raw) == len(ev) and np.array_equal(raw["timeStamp"], ev.t[order])
    if chip == "davis346":  # tonic decodes DAVIS346 addresses itself
        _, _, xytp = tonic_io.read_davis_346(str(path))
        assert np.array_equal(xytp["x"], back.x) and np.array_equal(xytp["y"], back.y)
        assert np.array_equal(xytp["p"], back.p > 0)


@pytest.mark.parametrize("y_raw", [140, 141, 142, 143])
def test_lone_first_event_in_a_hash_row_gets_a_special_record(tmp_path, y_raw):
    """No other event of the first time: a DAVIS special event goes first. jAER marks it
    special and evchain skips it; a reader that ignores the special bit (tonic) sees it as one
    OFF event at raw address 0 (the limit, documented)."""
    ev = hash_first("davis346", y_raw, n_same=1, seed=y_raw)
    path = write_aedat2(tmp_path / "x.aedat", ev)
    header = read_header(path)
    data = path.read_bytes()
    assert data[header.data_offset] != ord("#") and header.n_records == len(ev) + 1
    assert jaer_data_offset(data) == header.data_offset
    stats = DecodeStats()
    assert same(read_aedat2(path, stats=stats), ev)
    assert stats.skipped_non_dvs == 1
    tonic_io = pytest.importorskip("tonic.io")
    _, _, xytp = tonic_io.read_davis_346(str(path))
    assert len(xytp) == len(ev) + 1
    assert (xytp["x"][0], xytp["y"][0], xytp["p"][0]) == (345, 259, False)
    assert np.array_equal(xytp["x"][1:], ev.x) and np.array_equal(xytp["t"][1:], ev.t)


def test_generic_geometry_round_trip(tmp_path):
    ev = random_events(2000, Geometry(64, 48), seed=4)
    path = write_aedat2(tmp_path / "g.aedat", ev)
    assert b"# evchain-sensor: 64x48" in path.read_bytes()[:400]
    back = read_aedat2(path)
    assert back.geometry == Geometry(64, 48) and same(back, ev)


# --- timestamps ------------------------------------------------------------------------------

def test_wrap_is_unwrapped(tmp_path):
    ts = [2**32 - 10, 2**32 - 5, 3, 8, 2**31 + 1]
    path = raw_file(tmp_path / "w.aedat", davis([1] * 5, [1] * 5, [1] * 5), ts)
    for chunk in (1, 2, 100):
        stats = DecodeStats()
        ev = read_aedat2(path, chunk_records=chunk, stats=stats)
        assert ev.t.tolist() == [2**32 - 10, 2**32 - 5, 2**32 + 3, 2**32 + 8, 2**32 + 2**31 + 1]
        assert stats.wraps == 1


def test_signed_overflow_is_continuous(tmp_path):
    # jAER's int32 goes 2^31-1 -> -2^31: as unsigned that is one step forward
    ts = [2**31 - 2, 2**31 - 1, 2**31, 2**31 + 4]
    ev = read_aedat2(raw_file(tmp_path / "s.aedat", davis([1] * 4, [1] * 4, [0] * 4), ts))
    assert ev.t.tolist() == ts


def test_reset_continues_time(tmp_path):
    ts = [4_000_000, 5_000_000, 10, 60]
    stats = DecodeStats()
    ev = read_aedat2(raw_file(tmp_path / "r.aedat", davis([1] * 4, [1] * 4, [0] * 4), ts),
                     stats=stats)
    assert ev.t.tolist() == [4_000_000, 5_000_000, 5_000_000, 5_000_050]
    assert stats.resets == 1


def test_short_step_back_below_the_reset_window_is_no_reset(tmp_path):
    """500 ms then 495 ms: below 1 s, but nearer to the time before than to 0: an error (or
    clamped with a tolerance), not a reset that would hide it."""
    ts = [400_000, 500_000, 495_000, 510_000]
    path = raw_file(tmp_path / "s.aedat", davis([1] * 4, [1] * 4, [0] * 4), ts)
    with pytest.raises(DataError, match=r"s\.aedat: record 2 .*goes back from 500000 to "
                                        r"495000 us \(raw\), by 5000 us"):
        read_aedat2(path)
    stats = DecodeStats()
    ev = read_aedat2(path, backstep_tolerance_us=5000, stats=stats)
    assert ev.t.tolist() == [400_000, 500_000, 500_000, 510_000]
    assert stats.resets == 0 and stats.clamped == 1
    # a restart near 0 from only 500 ms is still a reset
    ts = [400_000, 500_000, 20, 30]
    stats = DecodeStats()
    ev = read_aedat2(raw_file(tmp_path / "r.aedat", davis([1] * 4, [1] * 4, [0] * 4), ts),
                     stats=stats)
    assert ev.t.tolist() == [400_000, 500_000, 500_000, 500_010] and stats.resets == 1


def test_reset_is_a_warning_in_the_report(tmp_path):
    from evchain.core.chain import run_pipeline
    from evchain.core.config import pipeline_from_text
    from evchain.core.registry import make_registry

    path = raw_file(tmp_path / "r.aedat", davis([1] * 4, [1] * 4, [0] * 4),
                    [4_000_000, 5_000_000, 10, 60])
    registry = make_registry(discover=False)
    text = f"chain:\n  - use: aedat\n    path: {path}\n    chip: davis240\n"
    rep = run_pipeline(pipeline_from_text(text, "t.yaml", registry), registry,
                       tmp_path / "run").report
    assert rep["status"] == "ok" and rep["metrics"]["aedat"]["resets"] == 1
    assert rep["warnings"] == [f"aedat: {path}: the timestamps were reset 1 time(s) (first at "
                               "record 2); time continues from the event before each reset, the "
                               "pause at a reset is unknown and counted as 0"]
    assert json.loads((tmp_path / "run" / "report.json").read_text())["warnings"] == \
        rep["warnings"]


def test_chip_parameter_that_contradicts_the_header_is_an_error(tmp_path):
    ev = random_events(20, Geometry(240, 180), seed=2)
    path = write_aedat2(tmp_path / "d240.aedat", ev)  # header: AEChip ... DAVIS240C
    with pytest.raises(DataError, match=r"d240\.aedat: the parameter chip is 'davis346' but the "
                                        r"header says 'AEChip: eu.seebetter.ini.chips.davis."
                                        r"DAVIS240C' \(davis240, 240x180\)"):
        read_aedat2(path, chip="davis346")
    assert len(read_aedat2(path, chip="davis240")) == 20


def test_backwards_beyond_a_wrap_is_an_error(tmp_path):
    ts = [3_000_000, 5_000_000, 4_000_000, 6_000_000]
    path = raw_file(tmp_path / "b.aedat", davis([1] * 4, [1] * 4, [0] * 4), ts)
    with pytest.raises(DataError, match=r"b\.aedat: record 2 \(byte offset \d+\): timestamp "
                                        r"goes back from 5000000 to 4000000"):
        read_aedat2(path)
    # small jitter can be clamped on request
    ts = [100, 2_000_000, 1_999_990, 2_000_005]
    path = raw_file(tmp_path / "j.aedat", davis([1] * 4, [1] * 4, [0] * 4), ts)
    with pytest.raises(DataError, match="j.aedat"):
        read_aedat2(path)
    ev = read_aedat2(path, backstep_tolerance_us=20)
    assert ev.t.tolist() == [100, 2_000_000, 2_000_000, 2_000_005]


# --- bad input -------------------------------------------------------------------------------

def test_missing_file(tmp_path):
    with pytest.raises(DataError, match=r"nope\.aedat: no such file"):
        read_aedat2(tmp_path / "nope.aedat")


def test_empty_file(tmp_path):
    (tmp_path / "e.aedat").write_bytes(b"")
    with pytest.raises(DataError, match=r"e\.aedat: empty file.*#!AER-DAT2\.0"):
        read_aedat2(tmp_path / "e.aedat")


@pytest.mark.parametrize("content", [b"\x89PNG\r\n\x1a\n" + bytes(100), b"hello world\n",
                                     b"# just a comment\r\n" + bytes(16)])
def test_not_aedat(tmp_path, content):
    (tmp_path / "n.aedat").write_bytes(content)
    with pytest.raises(DataError, match=r"n\.aedat: not an AEDAT file.*expected the first line"):
        read_aedat2(tmp_path / "n.aedat")


def test_other_aedat_version(tmp_path):
    (tmp_path / "v3.aedat").write_bytes(b"#!AER-DAT3.1\r\n#!END-HEADER\r\n" + bytes(28))
    with pytest.raises(DataError, match=r"v3\.aedat: AEDAT version '3\.1' is not supported"):
        read_aedat2(tmp_path / "v3.aedat")


def test_truncated_last_record(tmp_path):
    path = raw_file(tmp_path / "t.aedat", davis([1, 2], [1, 2], [0, 1]), [1, 2])
    offset = read_header(path).data_offset + 8
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(DataError, match=rf"t\.aedat: truncated last record at byte offset "
                                        rf"{offset} \(record 1\): 5 bytes"):
        read_aedat2(path)


def test_address_outside_sensor(tmp_path):
    path = raw_file(tmp_path / "o.aedat", davis([1, 300], [1, 2], [0, 1]), [1, 2])
    with pytest.raises(DataError, match=r"o\.aedat: record 1 \(byte offset \d+\).*raw "
                                        r"\(x=300, y=2\), outside the 240x180 sensor"):
        read_aedat2(path)
    path = raw_file(tmp_path / "y.aedat", davis([1], [200], [0]), [1])
    with pytest.raises(DataError, match=r"y\.aedat: record 0 .*outside"):
        read_aedat2(path)
    # a DAVIS file whose header names no chip, read as DVS128
    path = raw_file(tmp_path / "c.aedat", davis([1], [2], [0]), [1], chip=None)
    with pytest.raises(DataError, match=r"c\.aedat: record 0 .*DVS128 layout"):
        read_aedat2(path, chip="dvs128")


def test_header_without_chip_needs_the_parameter(tmp_path):
    path = raw_file(tmp_path / "nc.aedat", davis([1], [2], [0]), [1], chip=None)
    with pytest.raises(DataError, match=r"nc\.aedat: the header names no chip.*set the "
                                        r"parameter chip"):
        read_aedat2(path)
    assert len(read_aedat2(path, chip="davis240")) == 1


def test_header_only_file_has_no_events(tmp_path):
    path = tmp_path / "h.aedat"
    path.write_bytes(header_bytes(CHIPS["dvs128"]))
    ev = read_aedat2(path)
    assert len(ev) == 0 and ev.geometry == Geometry(128, 128)


# --- the stages ------------------------------------------------------------------------------

def make_file(tmp_path, n=20_000, gap=False) -> Path:
    g = CHIPS["davis240"].geometry
    ev = random_events(n, g, 1_000, 801_000, seed=2)
    if gap:  # no events for 300 ms in the middle
        ev = ev.replace(t=np.where(ev.t > 400_000, ev.t + 300_000, ev.t),
                        t_end=ev.t_end + 300_000)
    return write_aedat2(tmp_path / "s.aedat", ev)


def run_source(params: dict, tmp_path) -> tuple[list[EventPacket], Context]:
    ctx = Context(out_dir=tmp_path)
    src = AedatSource()
    src.id = "aedat"
    src.setup(AedatSource.Params(**params), ctx)
    try:
        return list(src.packets()), ctx
    finally:
        src.close()


def test_source_contract_and_slices(tmp_path):
    path = make_file(tmp_path, gap=True)
    check_source(AedatSource, {"path": str(path)}, out_dir=tmp_path, max_packets=1000)
    packets, ctx = run_source({"path": str(path), "packet_us": 10_000}, tmp_path)
    assert ctx.geometry == Geometry(240, 180)
    whole = read_aedat2(path)
    assert same(EventPacket.concat(packets), whole)
    for a, b in zip(packets, packets[1:], strict=False):
        assert a.t_end == b.t_start
    lengths = [p.t_end - p.t_start for p in packets]
    assert max(lengths) >= 280_000  # the empty slices of the gap became one packet
    assert sum(len(p) == 0 for p in packets) == 1
    assert ctx.metrics["aedat"]["events"] == len(whole)


def test_source_output_independent_of_chunk_size(tmp_path):
    path = make_file(tmp_path, n=3000)
    ref, _ = run_source({"path": str(path), "packet_us": 7_000}, tmp_path)
    got, _ = run_source({"path": str(path), "packet_us": 7_000, "chunk_records": 13}, tmp_path)
    assert [(p.t_start, p.t_end) for p in ref] == [(p.t_start, p.t_end) for p in got]
    assert same(EventPacket.concat(ref), EventPacket.concat(got))


def test_source_errors_name_the_file(tmp_path):
    with pytest.raises(DataError, match="missing.aedat"):
        run_source({"path": str(tmp_path / "missing.aedat")}, tmp_path)


@pytest.mark.skipif(not SHIPPED.exists(), reason="tests/data file not generated")
def test_shipped_quickstart_file_reads():
    ev = read_aedat2(SHIPPED)
    assert ev.geometry == Geometry(240, 180) and len(ev) > 1000
    assert SHIPPED.stat().st_size < 200_000


def test_writer_contract(tmp_path):
    g = CHIPS["davis240"].geometry
    ev = random_events(3000, g, 0, 100_000, seed=5)
    check_filter(AedatWriter, {"path": str(tmp_path / "w.aedat")}, recut([ev], [30_000]),
                 out_dir=tmp_path)
    assert same(read_aedat2(tmp_path / "w.aedat"), ev)


def test_writer_is_atomic(tmp_path):
    g = CHIPS["dvs128"].geometry
    ev = random_events(1000, g, 0, 100_000, seed=6)
    ctx = Context(out_dir=tmp_path, geometry=g)
    w = AedatWriter()
    w.id = "aedat_writer"
    w.setup(AedatWriter.Params(path="sub/out.aedat"), ctx)
    w.process(ev)
    w.close()  # a failed run: no flush
    assert not (tmp_path / "sub" / "out.aedat").exists()
    assert (tmp_path / "sub" / "out.aedat.partial").exists()
    # a successful one
    w = AedatWriter()
    w.id = "aedat_writer"
    w.setup(AedatWriter.Params(path="sub/out.aedat"), ctx)
    assert w.process(ev) is ev
    w.flush()
    w.close()
    assert same(read_aedat2(tmp_path / "sub" / "out.aedat"), ev)
    assert ctx.metrics["aedat_writer"]["events"] == len(ev)


def test_sensor_too_large_for_aedat2_fails_at_validation(monkeypatch):
    """A pipeline whose scene is larger than AEDAT 2.0 can address fails when it is loaded
    (before anything renders), naming the size's field and the writers to use instead."""
    from evchain.core.config import pipeline_from_text
    from evchain.core.registry import make_registry
    from evchain.errors import ConfigError
    from evchain.filters.scene import SceneSource

    setups = []
    monkeypatch.setattr(SceneSource, "setup", lambda *a: setups.append(a))
    text = ("chain:\n  - use: scene\n    width: {w}\n    height: {h}\n  - use: emulator\n"
            "  - use: aedat_writer\n{chip}")
    reg = make_registry()
    with pytest.raises(ConfigError) as err:
        pipeline_from_text(text.format(w=1280, h=720, chip=""), "p.yaml", reg)
    msg = str(err.value)
    assert msg.startswith("p.yaml:6:5: scene.width: stage 'aedat_writer' (aedat_writer): a "
                          "1280x720 sensor does not fit AEDAT 2.0")
    assert "at most 1024x512" in msg and "aedat4_writer" in msg and "hdf5_writer" in msg
    with pytest.raises(ConfigError, match="a 320x513 sensor does not fit AEDAT 2.0"):
        pipeline_from_text(text.format(w=320, h=513, chip=""), "p.yaml", reg)
    with pytest.raises(ConfigError, match="chip: a 320x240 sensor does not fit chip dvs128"):
        pipeline_from_text(text.format(w=320, h=240, chip="    chip: dvs128\n"), "p.yaml", reg)
    # the largest size that fits loads
    spec = pipeline_from_text(text.format(w=1024, h=512, chip=""), "p.yaml", reg)
    assert [s.use for s in spec.stages] == ["scene", "emulator", "aedat_writer"]
    assert setups == []                   # nothing was set up, let alone rendered


def test_sensor_too_large_for_aedat2_fails_at_setup(tmp_path):
    """A source whose size comes from its input sets it at setup; the writer refuses it
    there, before any packet."""
    w = AedatWriter()
    w.id = "out"
    with pytest.raises(ConfigError, match=r"out: a 1280x720 sensor does not fit AEDAT 2.0.*"
                                          r"aedat4_writer .*hdf5_writer"):
        w.setup(AedatWriter.Params(), Context(out_dir=tmp_path, geometry=Geometry(1280, 720)))


# --- kernels against the naive reference -----------------------------------------------------

@pytest.mark.parametrize("layout,w,h", [("davis", 240, 180), ("davis", 346, 260),
                                        ("dvs128", 128, 128)])
def test_kernels_match_naive(layout, w, h):
    from evchain.kernels.aedat2 import decode, encode
    from tests.naive import aedat2 as naive

    rng = np.random.default_rng(11)
    n = 3000
    if layout == "davis":
        addr = davis(rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n))
        odd = rng.random(n) < 0.1  # APS/IMU and special records mixed in
        addr[odd] |= rng.choice(np.array([0x80000000, 0x400, 0x80000C00], np.uint32),
                                int(odd.sum()))
    else:
        addr = ((rng.integers(0, h, n) << 8) | (rng.integers(0, w, n) << 1)
                | rng.integers(0, 2, n)).astype(np.uint32)
        addr[rng.random(n) < 0.1] |= np.uint32(1 << 15)
    ts = np.sort(rng.integers(0, 2**32, n)).astype(np.uint32)
    rec = np.empty((n, 2), ">u4")
    rec[:, 0], rec[:, 1] = addr, ts
    events, skipped, bad = naive.decode(rec.tobytes(), layout, w, h)
    assert bad is None
    x, y = np.empty(n, np.uint16), np.empty(n, np.uint16)
    t, p = np.empty(n, np.int64), np.empty(n, np.int8)
    words = rec.reshape(-1).view("<u4")
    code = 0 if layout == "davis" else 1
    k, kbad, back, kskip = decode(words, code, w, h, 0, np.iinfo(np.int64).min, x, y, t, p)
    assert (kbad, back, kskip) == (-1, -1, skipped)
    assert list(zip(x[:k].tolist(), y[:k].tolist(), t[:k].tolist(), p[:k].tolist(),
                    strict=True)) == events
    out = np.empty(2 * k, "<u4")
    assert encode(x[:k], y[:k], t[:k], p[:k], code, w, h, 0, out) == (-1, -1)
    assert out.tobytes() == naive.encode(events, layout, w, h)
    # hard inputs: an address outside the sensor, a backward step, a big gap
    rec[5, 0] = davis(w, 0, 0) if layout == "davis" else np.uint32(1 << 20)
    assert naive.decode(rec.tobytes(), layout, w, h)[2] == 5
    assert decode(words, code, w, h, 0, np.iinfo(np.int64).min, x, y, t, p)[1] == 5
    rec[5, 0] = rec[4, 0]
    rec[7, 1] = 0
    kk, kbad, back, _ = decode(words, code, w, h, 0, np.iinfo(np.int64).min, x, y, t, p)
    assert kbad == -1 and t[back] == 0 and back <= 7
    tt = np.array([0, 10, 2**31 + 10], np.int64)
    assert encode(x[:3], y[:3], tt, p[:3], code, w, h, 0, np.empty(6, "<u4"))[1] == 2


def test_writer_refuses_gaps_over_2_31_us(tmp_path):
    g = CHIPS["davis240"].geometry
    ev = EventPacket(geometry=g, t_start=0, t_end=2**31 + 10, x=np.array([1, 2], np.uint16),
                     y=np.array([1, 2], np.uint16), t=np.array([0, 2**31 + 5], np.int64),
                     p=np.array([1, 1], np.int8))
    with pytest.raises(DataError, match=r"gap\.aedat: event 1 .*gap of 2\^31 us"):
        write_aedat2(tmp_path / "gap.aedat", ev)
    assert not (tmp_path / "gap.aedat").exists()


def test_writer_refuses_events_outside_the_chip(tmp_path):
    ev = random_events(10, Geometry(128, 48), seed=1).replace(x=np.full(10, 150, np.uint16))
    with pytest.raises(DataError, match=r"big\.aedat: event 0 at \(150, \d+\) is outside the "
                                        r"128x128 sensor of chip dvs128"):
        write_aedat2(tmp_path / "big.aedat", ev, chip="dvs128")


# --- shipped data, quick start, failed runs --------------------------------------------------

def test_make_data_reproduces_the_shipped_file(tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_data", REPO / "tests/data/make_data.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = module.make(tmp_path / "again.aedat")
    assert out.read_bytes() == SHIPPED.read_bytes()


def test_quickstart_aedat_pipeline(tmp_path, monkeypatch):
    from evchain.core.chain import run_pipeline
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry
    from tests.naive.refractory import refractory as naive_refractory

    monkeypatch.chdir(REPO)
    registry = make_registry(discover=False)
    result = run_pipeline(load_pipeline("pipelines/quickstart-aedat.yaml", registry), registry,
                          tmp_path)
    assert result.report["status"] == "ok"
    out = read_aedat2(tmp_path / "on_events.aedat")
    ev = read_aedat2(SHIPPED)
    keep = np.array(naive_refractory(list(zip(ev.x.tolist(), ev.y.tolist(), ev.t.tolist(),
                                              ev.p.tolist(), strict=True)), 1000, False))
    expect = ev.select(keep & (ev.p > 0))
    assert len(expect) < np.count_nonzero(ev.p > 0)  # the hot pixel was thinned out
    assert same(out, expect)


def test_failed_run_leaves_no_complete_looking_output(tmp_path):
    from evchain.core.chain import run_pipeline
    from evchain.core.config import pipeline_from_text
    from evchain.core.registry import make_registry
    from evchain.errors import EvchainError

    n = 5000
    addr = davis(np.arange(n) % 200, np.arange(n) % 150, np.arange(n) % 2)
    addr[-1] = davis(239, 200, 1)  # the last record is outside the sensor: fails late
    bad = raw_file(tmp_path / "late_error.aedat", addr, np.arange(n) * 10)
    text = (f"name: t\nseed: 0\nchain:\n  - use: aedat\n    path: {bad}\n    packet_us: 1000\n"
            f"    chunk_records: 1000\n  - use: aedat_writer\n    path: out.aedat\n")
    registry = make_registry(discover=False)
    with pytest.raises(EvchainError, match=r"late_error\.aedat: record 4999"):
        run_pipeline(pipeline_from_text(text, "t.yaml", registry), registry, tmp_path / "run")
    assert not (tmp_path / "run" / "out.aedat").exists()
    assert (tmp_path / "run" / "out.aedat.partial").exists()
