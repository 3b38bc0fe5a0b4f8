"""imu_truth: gyro ground truth on a synthetic rolling camera, calibration, bad input, and on
the DVSFLOW16 recordings when they are there."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.core.series import IMU
from evchain.errors import DataError
from evchain.filters.imu_truth import ImuTruth
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import RollingCamera, moving_edge_events

REPO = Path(__file__).resolve().parents[2]
DVSFLOW = REPO / ".." / "shared" / "data" / "dvsflow16"
BIAS = (1.0, -0.5, 0.3)


def stream(cam: RollingCamera, packet_us: int = 10_000, **imu) -> list[EventPacket]:
    whole = cam.events().with_series(IMU.name, cam.imu(**imu))
    return recut([whole], list(range(packet_us, cam.duration_us, packet_us)))


def run(packets, **params):
    """Each output packet with the truth at its events as the scorer would ask for it (right
    after the stage released it), and the context."""
    f = ImuTruth()
    f.id = "imu_truth"
    ctx = Context(geometry=packets[0].geometry)
    f.setup(ImuTruth.Params(**params), ctx)
    outs = []
    for p in [*packets, None]:
        out = f.process(p) if p is not None else f.flush()
        if out is not None:
            outs.append((out, ctx.truth.flow(out.x, out.y, out.t)))
    whole = EventPacket.concat([o for o, _ in outs])
    u = np.concatenate([t[0] for _, t in outs])
    v = np.concatenate([t[1] for _, t in outs])
    return whole, u, v, ctx


def test_calibration_finds_the_principal_point_and_the_time_offset():
    cam = RollingCamera()                        # centre (44, 27) on an 80x60 sensor
    out, u, v, ctx = run(stream(cam, offset_us=8000, bias_dps=BIAS), gyro_bias_dps=BIAS,
                         focal_px=70.0, calibration_us=1_000_000)
    m = ctx.metrics["imu_truth"]
    c = m["camera"]
    assert c["principal_point_from"] == "estimated" and c["time_offset_from"] == "estimated"
    assert np.hypot(c["principal_point_px"][0] - 44.0, c["principal_point_px"][1] - 27.0) < 0.5
    assert abs(c["time_offset_us"] - 8000) <= 3000
    assert m["bins"] == {"total": 15, "valid": 15, "disagree": 0, "few_measurements": 0,
                         "no_gyro": 0}
    assert m["checks"]["axes"]["z"]["sign"] == "agrees"
    assert not m["checks"]["axes"]["x"]["checked"]
    assert abs(m["checks"]["gravity_roll"]["ratio"] - 1) < 0.01
    halves = m["calibration"]["estimate"]["principal_point_halves_px"]
    assert all(np.hypot(h[0] - 44.0, h[1] - 27.0) < 1.0 for h in halves)
    # the truth: the rolling camera's flow wherever it is at least min_speed_pxs
    tu, tv = cam.flow(out.x, out.y, out.t)
    ok = np.isfinite(u)
    speed = np.hypot(tu, tv)
    assert ok.mean() > 0.9 and m["events"]["share_with_truth"] == pytest.approx(ok.mean())
    # only the slow ones near the centre are out, and those after the gyro's last sample
    assert np.all(speed[~ok & (out.t < cam.duration_us - 20_000)] < 10.5)
    rel = np.hypot(u - tu, v - tv)[ok] / speed[ok]
    assert np.median(rel) < 0.02                 # 2-3 ms offset error at 7.5 rad/s^2
    assert len(out) == len(cam.events())         # every event passes, none twice
    rate = out.series["imu_rate"]
    assert len(rate) == 15 and np.all(rate["valid"] == 1)
    np.testing.assert_allclose(rate["fit_gz"], rate["gz"], rtol=0.08)


def test_given_camera_gives_the_exact_flow():
    cam = RollingCamera()
    out, u, v, ctx = run(stream(cam, offset_us=-5000, bias_dps=BIAS), gyro_bias_dps=BIAS,
                         focal_px=70.0, principal_point_px=(44.0, 27.0), time_offset_us=-5000,
                         calibration_us=500_000)
    tu, tv = cam.flow(out.x, out.y, out.t)
    ok = np.isfinite(u)
    rel = np.hypot(u - tu, v - tv)[ok] / np.hypot(tu, tv)[ok]
    assert ok.mean() > 0.9 and rel.max() < 1e-3   # linear between 1 kHz samples
    assert ctx.metrics["imu_truth"]["camera"]["principal_point_from"] == "given"


def test_bias_from_a_still_start():
    cam = RollingCamera(duration_us=1_200_000)
    ev = cam.events()
    still = 600_000
    imu = cam.imu(bias_dps=BIAS, noise_dps=0.2, seed=3)
    rest = IMU.array(t=np.arange(0, still, 1000), ax=0.0, ay=-1.0, az=0.0,
                     gx=BIAS[0], gy=BIAS[1], gz=BIAS[2], temperature_c=30.0)
    rng = np.random.default_rng(4)
    for k in ("gx", "gy", "gz"):
        rest[k] += rng.normal(0, 0.2, len(rest))
    moved = imu.copy()
    moved["t"] += still
    whole = ev.replace(t=ev.t + still, t_end=ev.t_end + still).with_series(
        IMU.name, np.concatenate([rest, moved]))
    packets = recut([whole], list(range(10_000, whole.t_end, 10_000)))
    _, u, _, ctx = run(packets, focal_px=70.0, calibration_us=1_200_000)
    c = ctx.metrics["imu_truth"]["camera"]
    assert c["gyro_bias_from"].startswith("still stretch: 3 x 200 ms from 0.000 s")
    np.testing.assert_allclose(c["gyro_bias_dps"], BIAS, atol=0.03)
    assert np.isfinite(u).mean() > 0.8


def test_no_still_stretch_and_no_bias_is_a_clear_error():
    with pytest.raises(DataError, match="no still stretch in the first 1 s to take the gyro "
                                        "bias from.*give gyro_bias_dps"):
        run(stream(RollingCamera(duration_us=1_200_000)), calibration_us=1_000_000)


def test_no_imu_samples_is_a_clear_error():
    ev = RollingCamera(duration_us=300_000).events().with_series(IMU.name,
                                                                 np.zeros(0, IMU.dtype))
    with pytest.raises(DataError, match="the input carries no IMU samples .* the source's file "
                                        "has no IMU records"):
        run(recut([ev], [100_000, 200_000]), gyro_bias_dps=BIAS)


def test_wrong_roll_sign_gives_no_truth_and_says_so():
    cam = RollingCamera()
    out, u, _, ctx = run(stream(cam), gyro_bias_dps=(0, 0, 0), focal_px=70.0,
                         axis_signs=(1, 1, -1), calibration_us=1_000_000)
    assert np.isfinite(u).mean() == 0
    w = " ".join(ctx.warnings)
    assert "principal point and time offset not estimated" in w and "axis_signs" in w
    assert "the gyro's flow is the truth for only 0.0 % of the events" in w
    assert ctx.metrics["imu_truth"]["bins"]["disagree"] == 15


def test_translation_is_not_scored():
    """An edge translating across the sensor while the gyro says the camera rolls: the events
    contradict a pure rotation, so no event gets truth."""
    g = Geometry(80, 60)
    edges = [moving_edge_events(60.0, 20.0, g, 400_000, offset_px=o) for o in (0, -12, -24)]
    ev = EventPacket.concat([e.replace(t=e.t + 400_000 * i, t_start=400_000 * i,
                                       t_end=400_000 * (i + 1)) for i, e in enumerate(edges)])
    imu = RollingCamera(geometry=g, duration_us=1_200_000).imu()
    packets = recut([ev.with_series(IMU.name, imu)], list(range(20_000, 1_200_000, 20_000)))
    _, u, _, ctx = run(packets, gyro_bias_dps=(0, 0, 0), focal_px=70.0,
                       calibration_us=600_000, min_measurements=20)
    bins = ctx.metrics["imu_truth"]["bins"]
    assert np.isfinite(u).sum() == 0 and bins["valid"] == 0 and bins["disagree"] > 0


def test_previous_sample_interpolation():
    """jAER's model: the latest sample at or before the event time."""
    cam = RollingCamera(duration_us=600_000)
    packets = stream(cam)
    out, u, v, _ = run(packets, gyro_bias_dps=(0, 0, 0), focal_px=70.0,
                       principal_point_px=(44.0, 27.0), time_offset_us=0,
                       interpolation="previous", calibration_us=200_000)
    ok = np.isfinite(u)
    held = (out.t // 1000) * 1000                 # 1 kHz samples
    tu, tv = cam.flow(out.x, out.y, held)
    np.testing.assert_allclose(u[ok], tu[ok], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(v[ok], tv[ok], rtol=1e-9, atol=1e-9)


def test_contract_on_the_rolling_camera(tmp_path):
    cam = RollingCamera(duration_us=500_000)
    ref = check_filter(ImuTruth, {"gyro_bias_dps": BIAS, "focal_px": 70.0,
                                  "calibration_us": 250_000, "max_offset_us": 20_000},
                       stream(cam, packet_us=25_000, bias_dps=BIAS), out_dir=tmp_path)
    assert len(ref["series:imu_rate"]) == 5 and len(ref["t"]) == len(cam.events())


@pytest.mark.skipif(not (DVSFLOW / "IMU_rotDisk.aedat").is_file(),
                    reason="DVSFLOW16 IMU recordings not available")
@pytest.mark.parametrize("name", ["IMU_rotDisk", "IMU_translBoxes"])
def test_dvsflow16_recordings(name, tmp_path):
    """rotDisk: the flow turns with the gyro's roll, about a centre 11-14 px right of the
    sensor's, and nearly all events get truth; translBoxes (the camera translates): none."""
    from evchain.cli import main

    path = DVSFLOW / f"{name}.aedat"
    pipeline = REPO / "pipelines" / "dvsflow16-imu-lk.yaml"
    assert main(["run", str(pipeline), "--set", f"aedat.path={path}",
                 "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    m = report["metrics"]["imu_truth"]
    share = m["events"]["share_with_truth"]
    if name == "IMU_rotDisk":
        dx, dy = m["camera"]["principal_point_minus_sensor_centre_px"]
        assert 11 <= dx <= 14 and abs(dy) < 12
        assert m["checks"]["axes"]["z"]["sign"] == "agrees"
        assert abs(m["checks"]["gravity_roll"]["ratio"] - 1) < 0.03
        assert abs(m["camera"]["time_offset_us"]) <= 10_000
        assert share > 0.9 and report["metrics"]["flow"]["n_scored"] > 30_000
    else:
        assert share < 0.05 and report["metrics"]["flow"]["n_scored"] < 0.05 * report[
            "metrics"]["flow"]["n_flow"]
        assert any("truth for only" in w for w in report["warnings"])


def test_rate_plot_of_the_rolling_camera(tmp_path):
    from evchain.filters.imu_rate_plot import ImuRatePlot

    cam = RollingCamera(duration_us=600_000)
    out, _, _, ctx = run(stream(cam, bias_dps=BIAS), gyro_bias_dps=BIAS, focal_px=70.0,
                         calibration_us=300_000)
    plot = ImuRatePlot()
    plot.id = "imu_rate_plot"
    plot.setup(ImuRatePlot.Params(path="rate.png"), Context(out_dir=tmp_path))
    assert plot.process(out) is out
    plot.flush()
    png = (tmp_path / "rate.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000
    assert plot.context.metrics["imu_rate_plot"]["bins"] == 6


def test_pipeline_on_a_file_without_imu_records_says_so(tmp_path, capsys):
    """A recording without IMU records: exit code 2 and a message naming the cause, no
    metrics that look like a result."""
    from evchain.cli import main
    from evchain.io.aedat2 import write_aedat2

    events = RollingCamera(Geometry(240, 180), centre=(120.0, 90.0),
                           duration_us=300_000).events()
    path = write_aedat2(tmp_path / "no_imu.aedat", events, chip="davis240")
    pipeline = REPO / "pipelines" / "dvsflow16-imu-lk.yaml"
    code = main(["run", str(pipeline), "--set", f"aedat.path={path}",
                 "--out", str(tmp_path / "run")])
    assert code == 2
    err = capsys.readouterr().err
    assert "imu_truth" in err and "no IMU samples" in err and "no IMU records" in err
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["status"] == "failed" and "flow" not in report["metrics"]


def test_rotation_truth_scores_an_estimated_rate():
    """The gyro's rate is the stage's RotationTruth (the rolling camera's, offset and bias
    removed), and foe_ttc_scorer after imu_truth scores a rate estimate against it: an
    estimate off by (2, 0, -3) deg/s scores sqrt(13); the FOE is not scored (undefined)."""
    from evchain.core.packets import FlowPacket
    from evchain.core.series import FOE, ROTATION_FIELDS
    from evchain.core.truth import RotationTruth
    from evchain.filters.foe_ttc_scorer import FoeTtcScorer

    cam = RollingCamera(duration_us=800_000)
    f = ImuTruth()
    f.id = "imu_truth"
    ctx = Context(geometry=cam.geometry)
    f.setup(ImuTruth.Params(gyro_bias_dps=BIAS, focal_px=70.0, principal_point_px=(44.0, 27.0),
                            time_offset_us=-5000, calibration_us=300_000), ctx)
    assert isinstance(ctx.truth, RotationTruth)
    scorer = FoeTtcScorer()
    scorer.id = "foe_ttc_scorer"
    scorer.setup(FoeTtcScorer.Params(plots=False, warmup_s=0.0), ctx)
    off = np.array([2.0, 0.0, -3.0])
    n_ticks, rates = 0, []
    for p in [*stream(cam, offset_us=-5000, bias_dps=BIAS), None]:
        out = f.process(p) if p is not None else f.flush()
        if out is None or out.t_end <= out.t_start:
            continue
        t = np.arange(out.t_start, out.t_end, 5_000, dtype=np.int64)
        wx, wy, wz = ctx.truth.angular_velocity(t)
        ok = np.isfinite(wz)
        np.testing.assert_allclose(wz[ok], cam.omega_z(t[ok]), atol=1e-4)
        np.testing.assert_allclose(np.hypot(wx[ok], wy[ok]), 0.0, atol=1e-9)
        true_deg = np.degrees(np.stack([wx, wy, wz], 1))
        foe = FOE.array(t=t, x=40.0, y=30.0, support=1.0, total=1.0,
                        rotation=np.where(ok, 1, 0))
        for i, c in enumerate(ROTATION_FIELDS):
            foe[c] = np.where(ok, true_deg[:, i] + off[i], 0.0)
        scorer.process(FlowPacket.empty(out.geometry, out.t_start, out.t_end)
                       .with_series(FOE.name, foe))
        n_ticks += int(ok.sum())
        rates.append(np.degrees(np.abs(cam.omega_z(t[ok]))))
    scorer.flush()
    m = ctx.metrics["foe"]
    assert n_ticks > 80
    assert m["rotation_rate_error_deg_s"] == pytest.approx(np.sqrt(13.0), abs=1e-3)
    assert m["rotation_rate_error_wz_deg_s"] == pytest.approx(3.0, abs=1e-3)
    assert m["rotation_rate_true_deg_s"] == pytest.approx(np.median(np.concatenate(rates)),
                                                          rel=1e-4)
    assert m["n"] == 0 and "the true FOE is undefined" in m["why_none"]
    x, y = ctx.truth.foe(np.array([1.0, 2.0]))
    assert np.isnan(x).all() and np.isnan(y).all() and np.isnan(ctx.truth.ttc(3.0))
