"""DAVIS IMU samples in AEDAT 2.0 files: layout, full scales, camera axes, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.series import IMU
from evchain.errors import DataError
from evchain.io.aedat2 import CHIPS, AedatSource, header_bytes, read_aedat2, read_imu
from evchain.io.davis_imu import encode_samples, scales_from_header
from evchain.testing.contract import check_source

REPO = Path(__file__).resolve().parents[2]
DVSFLOW = REPO / ".." / "shared" / "data" / "dvsflow16"
ROT_DISK = DVSFLOW / "IMU_rotDisk.aedat"

#: jAER's preference lines for a gyro at 1000 deg/s and an accelerometer at 8 g
JAER_PREFS = ['<entry key="CPLDByte.imu3_GYRO_CONFIG" value="16"/>',
              '<entry key="CPLDByte.imu4_ACCEL_CONFIG" value="16"/>',
              '<entry key="ImuGyroScale" value="GyroFullScaleDegPerSec1000"/>',
              '<entry key="ImuAccelScale" value="ImuAccelScaleG8"/>']


def dvs(x_raw, y_raw, on):
    return (np.uint32(y_raw) << np.uint32(22)) | (np.uint32(x_raw) << np.uint32(12)) | (
        np.uint32(on) << np.uint32(11))


def write(path: Path, records: np.ndarray, chip: str = "davis240", prefs=JAER_PREFS) -> Path:
    rec = np.asarray(records, np.uint64).astype(np.uint32).astype(">u4")
    path.write_bytes(header_bytes(CHIPS[chip], list(prefs)) + rec.tobytes())
    return path


def interleaved(n_samples: int = 20, dt_us: int = 1000, t0: int = 5_000, seed: int = 0,
                before_first_event: int = 1):
    """Records: IMU samples every ``dt_us`` with two DVS events between them (the first
    ``before_first_event`` samples come before any event); returns records, the raw readings,
    the sample times and the events ``(x_raw, y_raw, on, t)``."""
    rng = np.random.default_rng(seed)
    raw = rng.integers(-30000, 30000, (n_samples, 7)).astype(np.int16)
    t_imu = t0 + dt_us * np.arange(n_samples)
    imu_rec = encode_samples(t_imu, raw).reshape(n_samples, 7, 2)
    rows, events = [], []
    for i in range(n_samples):
        rows.extend(imu_rec[i])
        if i >= before_first_event - 1 and i < n_samples - 1:
            for k in (1, 2):
                x, y, on, t = int(rng.integers(0, 240)), int(rng.integers(0, 180)), k % 2, \
                    int(t_imu[i] + k * dt_us // 3)
                rows.append([dvs(x, y, on), t])
                events.append((x, y, on, t))
    return np.array(rows, np.uint64), raw, t_imu, events


def source_packets(path, **params):
    src = AedatSource()
    src.id = "aedat"
    ctx = Context()
    src.setup(AedatSource.Params(path=str(path), **params), ctx)
    return list(src.packets()), ctx


def test_samples_in_camera_axes_and_units(tmp_path):
    rec, raw, t_imu, events = interleaved()
    packets, ctx = source_packets(write(tmp_path / "a.aedat", rec), packet_us=3000)
    imu = np.concatenate([p.series["imu"] for p in packets])
    assert imu.dtype == IMU.dtype
    np.testing.assert_array_equal(imu["t"], t_imu)
    r = raw.astype(np.float64)
    # 8 g: 4096 LSB/g; 1000 deg/s: 32.8 LSB per deg/s; camera axes: x and z of the chip flipped
    np.testing.assert_allclose(imu["ax"], -r[:, 0] / 4096)
    np.testing.assert_allclose(imu["ay"], r[:, 1] / 4096)
    np.testing.assert_allclose(imu["az"], -r[:, 2] / 4096)
    np.testing.assert_allclose(imu["temperature_c"], r[:, 3] / 340 + 35)
    np.testing.assert_allclose(imu["gx"], -r[:, 4] / 32.8)
    np.testing.assert_allclose(imu["gy"], r[:, 5] / 32.8)
    np.testing.assert_allclose(imu["gz"], -r[:, 6] / 32.8)
    for p in packets:       # each sample in the packet whose slice holds it
        p.validate()
        assert np.all((p.series["imu"]["t"] >= p.t_start) & (p.series["imu"]["t"] < p.t_end))
    m = ctx.metrics["aedat"]
    assert m["imu_samples"] == 20 and m["skipped_non_dvs"] == 0 and m["imu_dropped_records"] == 0
    assert m["imu_full_scale"] == {"gyro_dps": 1000, "accel_g": 8,
                                   "from": "header ImuGyroScale/ImuAccelScale"}
    # the events are those of the file, the first IMU sample (before them) starts the stream
    ev = read_aedat2(tmp_path / "a.aedat")
    assert len(ev) == len(events) == m["events"]
    np.testing.assert_array_equal(ev.x, 239 - np.array([e[0] for e in events]))
    assert packets[0].t_start == t_imu[0] and packets[-1].t_end == t_imu[-1] + 1


def test_samples_split_across_chunks_and_read_imu(tmp_path):
    rec, raw, t_imu, _ = interleaved(n_samples=30, seed=2)
    path = write(tmp_path / "b.aedat", rec)
    whole = read_imu(path)
    for chunk in (1, 3, 5, 7, 11):
        packets, ctx = source_packets(path, chunk_records=chunk, packet_us=2000)
        got = np.concatenate([p.series["imu"] for p in packets])
        np.testing.assert_array_equal(got, whole)
        assert ctx.metrics["aedat"]["imu_samples"] == 30
        np.testing.assert_array_equal(read_imu(path, chunk_records=chunk), whole)
    assert len(whole) == 30


def test_incomplete_samples_are_dropped_and_counted(tmp_path):
    rec, raw, t_imu, _ = interleaved(n_samples=10)
    is_imu = (rec[:, 0] & 0x80000C00) == 0x80000C00
    imu_rows = np.flatnonzero(is_imu)
    lose = imu_rows[7 * 3 + 4]            # sample 3 loses its gyro x record
    rec = np.delete(rec, lose, axis=0)
    rec = rec[:-3]                        # and the file ends inside the last sample
    packets, ctx = source_packets(write(tmp_path / "c.aedat", rec))
    imu = np.concatenate([p.series["imu"] for p in packets])
    assert len(imu) == 8 and 3 * 1000 + 5000 not in imu["t"]
    m = ctx.metrics["aedat"]
    assert m["imu_samples"] == 8 and m["imu_dropped_records"] == 6 + 4
    assert any("IMU record(s) formed no complete sample" in w for w in ctx.warnings)


def test_scales_from_the_header():
    assert scales_from_header(JAER_PREFS).gyro_dps == 1000
    assert scales_from_header(JAER_PREFS).accel_g == 8
    # registers only: FS_SEL in bits 3-4 (0: 250 deg/s, 2 g ... 3: 2000 deg/s, 16 g)
    only_regs = ['<entry key="CPLDByte.imu3_GYRO_CONFIG" value="24"/>',
                 '<entry key="CPLDByte.imu4_ACCEL_CONFIG" value="0"/>']
    s = scales_from_header(only_regs)
    assert (s.gyro_dps, s.accel_g) == (2000, 2) and "register" in s.source
    assert scales_from_header(["# nothing"]).gyro_dps is None
    with pytest.raises(DataError, match="disagrees with the register"):
        scales_from_header([JAER_PREFS[0], '<entry key="ImuGyroScale" '
                                           'value="GyroFullScaleDegPerSec500"/>'])
    with pytest.raises(DataError, match="expected one of 250, 500, 1000, 2000"):
        scales_from_header(['<entry key="ImuGyroScale" value="GyroFullScaleDegPerSec300"/>'])


def test_no_range_info_is_a_clear_error_and_parameters_fill_it(tmp_path):
    rec, raw, _, _ = interleaved()
    path = write(tmp_path / "d.aedat", rec, prefs=[])
    with pytest.raises(DataError, match=r"d.aedat: record \d+ is an IMU sample, but the header "
                                        r"does not say the IMU's full scale.*gyro_full_scale_dps"
                                        r".*accel_full_scale_g.*imu: false"):
        source_packets(path)
    packets, ctx = source_packets(path, gyro_full_scale_dps=2000, accel_full_scale_g=2)
    imu = np.concatenate([p.series["imu"] for p in packets])
    np.testing.assert_allclose(imu["gy"], raw[:, 5] / 16.4)
    np.testing.assert_allclose(imu["ay"], raw[:, 1] / 16384)
    assert ctx.metrics["aedat"]["imu_full_scale"]["from"] == "parameters"
    packets, ctx = source_packets(path, imu=False)          # events only: no need for ranges
    assert "imu" not in packets[0].series and ctx.metrics["aedat"]["skipped_non_dvs"] == 140


def test_a_parameter_that_contradicts_the_header_is_an_error(tmp_path):
    path = write(tmp_path / "e.aedat", interleaved()[0])
    with pytest.raises(DataError, match="gyro_full_scale_dps is 500 but the header says the gyro "
                                        "full scale is 1000"):
        source_packets(path, gyro_full_scale_dps=500)


def test_non_dvs_error_spares_imu_records_but_not_aps(tmp_path):
    rec, _, _, _ = interleaved()
    packets, ctx = source_packets(write(tmp_path / "f.aedat", rec), non_dvs="error")
    assert ctx.metrics["aedat"]["imu_samples"] == 20
    aps = np.array([[0x80000000 | (5 << 12), int(rec[-1, 1])]], np.uint64)   # an APS sample
    with pytest.raises(DataError, match="non-DVS record"):
        source_packets(write(tmp_path / "g.aedat", np.concatenate([rec, aps])), non_dvs="error")
    with pytest.raises(DataError, match="non-DVS record"):
        source_packets(write(tmp_path / "h.aedat", rec), non_dvs="error", imu=False)


def test_imu_across_a_timestamp_wrap(tmp_path):
    rec, raw, t_imu, _ = interleaved(t0=(1 << 32) - 7_500)
    rec[:, 1] &= 0xFFFFFFFF                   # the file's 32-bit timestamps wrap mid-stream
    packets, _ = source_packets(write(tmp_path / "w.aedat", rec), packet_us=2000)
    imu = np.concatenate([p.series["imu"] for p in packets])
    np.testing.assert_array_equal(imu["t"], t_imu)
    for p in packets:
        p.validate()


def test_davis346_layout(tmp_path):
    rec, raw, t_imu, events = interleaved()
    packets, ctx = source_packets(write(tmp_path / "346.aedat", rec, chip="davis346"))
    imu = np.concatenate([p.series["imu"] for p in packets])
    assert ctx.metrics["aedat"]["chip"] == "davis346"
    np.testing.assert_allclose(imu["gz"], -raw[:, 6] / 32.8)
    assert packets[0].geometry.width == 346


def test_source_contract_with_imu(tmp_path):
    rec, _, _, _ = interleaved(n_samples=40)
    packets = check_source(AedatSource, {"path": str(write(tmp_path / "k.aedat", rec)),
                                         "packet_us": 5000}, out_dir=tmp_path)
    assert sum(len(p.series["imu"]) for p in packets) == 40


@pytest.mark.skipif(not ROT_DISK.is_file(), reason="DVSFLOW16 IMU recordings not available")
def test_rot_disk_gyro_rolls_about_the_optical_axis():
    """IMU_rotDisk: the camera rolls at about 30 deg/s about its optical axis (z); the other
    axes read only their bias (a few deg/s); gravity (about 1 g) turns in the image plane."""
    imu = read_imu(ROT_DISK)
    assert len(imu) == 7384
    assert np.all(np.diff(imu["t"]) > 0)
    assert 350 < np.median(np.diff(imu["t"])) < 450          # about 2.5 kHz
    gz = imu["gz"]
    assert -35 < gz.mean() < -25 and np.all(gz < -10)
    assert abs(imu["gx"].mean()) < 5 and abs(imu["gy"].mean()) < 5
    a = np.sqrt(imu["ax"] ** 2 + imu["ay"] ** 2 + imu["az"] ** 2)
    assert abs(np.median(a) - 1.0) < 0.05
    assert imu["ay"][:50].mean() < -0.9                      # upright at the start
    assert 20 < imu["temperature_c"].mean() < 45
    # gravity turns the other way than the camera rolls, by about as much
    psi = np.degrees(np.unwrap(np.arctan2(imu["ay"], imu["ax"])))
    turn = -np.sum(0.5 * (gz[1:] + gz[:-1]) * np.diff(imu["t"]) * 1e-6)
    assert abs((psi[-1] - psi[0]) / turn - 1) < 0.05


def test_a_file_without_imu_records_gives_no_series(tmp_path):
    rec = np.array([[dvs(3, 4, 1), 1000], [dvs(5, 6, 0), 2000]], np.uint64)
    packets, ctx = source_packets(write(tmp_path / "plain.aedat", rec))
    assert all("imu" not in p.series for p in packets)
    assert ctx.metrics["aedat"]["imu_samples"] == 0
