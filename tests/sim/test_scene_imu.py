"""The scene's simulated IMU and the rotating camera: true gyro and accelerometer, the IMU
series through the emulator, and imu_truth fed by the simulated gyro against the renderer's
exact flow."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.series import IMU
from evchain.errors import ConfigError
from evchain.filters.emulator import Emulator
from evchain.filters.imu_truth import ImuTruth
from evchain.filters.scene import SceneSource
from evchain.sim.drive import Scene
from evchain.sim.imu import imu_between, sample_normals, true_imu
from evchain.testing.contract import check_source

ROTATION = dict(scenario="high-rise", start_m=120.0, dynamics="rotation", speed_mps=0.0,
                duration_s=1.2, pan_dps=20.0, tilt_dps=6.0, rotation_start_s=0.4,
                width=160, height=120, supersample=1)


def test_true_imu_of_turning_and_driving_cameras():
    scene = Scene.from_params(**{**ROTATION, "width": 16, "height": 12})
    gyro, accel = true_imu(scene, np.array([0, 300_000, 900_000]))
    np.testing.assert_allclose(gyro[:2], 0.0, atol=1e-12)            # at rest until 0.4 s
    np.testing.assert_allclose(accel[0], [0.0, -1.0, 0.0], atol=1e-9)  # upright: up is -y
    tilt = np.radians(6.0 * 0.5)
    np.testing.assert_allclose(gyro[2], [6.0, 20 * np.cos(tilt), -20 * np.sin(tilt)],
                               atol=1e-9)      # the vertical pan axis, seen from a tilted camera
    np.testing.assert_allclose(accel[2], [0.0, -np.cos(tilt), np.sin(tilt)], atol=1e-6)
    # a car in a left curve of radius 40 m at 20 m/s: yaw left, 10 m/s^2 towards the left
    curve = Scene.from_params(scenario="curves", dynamics="curves", start_m=80.0,
                              duration_s=0.5, width=16, height=12)
    gyro, accel = true_imu(curve, np.array([200_000]))
    np.testing.assert_allclose(gyro[0], [0.0, -np.degrees(20 / 40), 0.0], atol=1e-9)
    np.testing.assert_allclose(accel[0], [-400 / 40 / 9.80665, -1.0, 0.0], atol=1e-6)


def test_rotation_dynamics_rules():
    with pytest.raises(ConfigError, match="turns the camera in place: set speed_mps 0"):
        Scene.from_params(**{**ROTATION, "speed_mps": 5.0})
    with pytest.raises(ConfigError, match="apply to dynamics 'rotation'"):
        Scene.from_params(scenario="high-rise", pan_dps=5.0, duration_s=1.0)
    with pytest.raises(ConfigError, match="at most 80"):
        Scene.from_params(**{**ROTATION, "tilt_dps": 150.0})


def scene_packets(**imu):
    src = SceneSource()
    src.id = "scene"
    ctx = Context(seed=3)
    src.setup(SceneSource.Params(**ROTATION, imu_rate_hz=1000, **imu), ctx)
    return src, ctx, list(src.packets())


def test_scene_source_emits_the_imu_series():
    src, ctx, packets = scene_packets(imu_gyro_noise_dps=0.2, imu_gyro_bias_dps=(1.0, 0, 0))
    imu = np.concatenate([p.series["imu"] for p in packets])
    np.testing.assert_array_equal(imu["t"], np.arange(0, 1_200_000, 1000))
    for p in packets:
        assert np.all((p.series["imu"]["t"] >= p.t_start) & (p.series["imu"]["t"] < p.t_end))
    gyro, _ = true_imu(src.scene, imu["t"])
    dev = imu["gx"] - gyro[:, 0] - 1.0
    assert abs(dev.mean()) < 0.03 and 0.17 < dev.std() < 0.23      # bias and noise as set
    again = np.concatenate([p.series["imu"] for p in scene_packets(
        imu_gyro_noise_dps=0.2, imu_gyro_bias_dps=(1.0, 0, 0))[2]])
    np.testing.assert_array_equal(again, imu)                      # seeded
    check_source(SceneSource, {**ROTATION, "width": 32, "height": 24, "duration_s": 0.05,
                               "imu_rate_hz": 500})


def test_imu_noise_is_standard_normal_per_sample_and_column():
    """Counter-based noise: standard normal (Kolmogorov-Smirnov against N(0, 1)), columns
    and neighbouring samples uncorrelated, other keys other values, the same key and time the
    same values whichever other samples are drawn with them."""
    from scipy import stats

    t = np.arange(0, 200_000_000, 1000, dtype=np.int64)          # 200 000 samples at 1 kHz
    z = sample_normals(12345, t, 6)
    assert z.shape == (len(t), 6) and np.isfinite(z).all()
    for j in range(6):
        assert stats.kstest(z[:, j], "norm").pvalue > 1e-3
    corr = np.corrcoef(np.hstack([z[1:], z[:-1]]).T)
    np.fill_diagonal(corr, 0.0)
    assert np.abs(corr).max() < 0.015                             # ~3 sigma of 1/sqrt(n)
    assert np.abs(z - sample_normals(12346, t, 6)).min(axis=1).max() > 0
    np.testing.assert_array_equal(sample_normals(12345, t[::7], 6), z[::7])
    # the extremes of a 53-bit uniform stay finite: u = 0 gives r = 0, u -> 1 a large r
    assert np.isfinite(sample_normals(0, np.array([0, -1, 2**62]), 5)).all()


def test_imu_noise_does_not_depend_on_the_packets():
    """The same drive cut into other slices has the same noisy samples (what lets a replay,
    whose packets are fixed slices, carry its recording's IMU)."""
    scene = Scene.from_params(**{**ROTATION, "width": 16, "height": 12})
    noise = (1000.0, 99, 0.3, (0.5, 0.0, 0.0), 0.02)     # rate, key, gyro noise, bias, accel
    whole = imu_between(scene, 0, 600_000, *noise)
    cuts = [0, 7_000, 123_456, 300_001, 600_000]
    parts = np.concatenate([imu_between(scene, a, b, *noise)
                            for a, b in zip(cuts[:-1], cuts[1:], strict=True)])
    np.testing.assert_array_equal(parts, whole)
    quiet = imu_between(scene, 0, 600_000, 1000.0, 99)
    assert 0.25 < np.std(whole["gx"] - quiet["gx"]) < 0.35
    assert 0.015 < np.std(whole["az"] - quiet["az"]) < 0.025


def through_imu_truth(packets, ctx, **params):
    """Scene packets through the emulator and imu_truth; per output packet its events with
    the scene's exact flow and imu_truth's flow there, asked when the stage released them."""
    emu = Emulator()
    emu.id = "emulator"
    emu.setup(Emulator.Params(), ctx)
    exact = ctx.truth
    it = ImuTruth()
    it.id = "imu_truth"
    it.setup(ImuTruth.Params(**params), ctx)
    rows = []

    def keep(out):
        if out is not None and len(out):
            rows.append((out.x, out.y, out.t, *exact.flow(out.x, out.y, out.t),
                         *ctx.truth.flow(out.x, out.y, out.t)))

    for p in packets:
        ev = emu.process(p)
        assert IMU.name in ev.series              # the emulator passes the IMU on
        keep(it.process(ev))
    last = emu.flush()
    if last is not None:
        keep(it.process(last))
    keep(it.flush())
    return [np.concatenate(c) for c in zip(*rows, strict=True)], ctx


def test_imu_truth_fed_by_the_simulated_gyro_is_the_exact_flow():
    src, ctx, packets = scene_packets()
    g = ctx.geometry
    (x, y, t, ux, uy, gx, gy), ctx = through_imu_truth(
        packets, ctx, focal_px=g.f, principal_point_px=(g.cx, g.cy), time_offset_us=0,
        gyro_bias_dps=(0.0, 0.0, 0.0), calibration_us=1_200_000)
    ok = np.isfinite(gx)
    assert ok.mean() > 0.8
    rel = np.hypot(gx - ux, gy - uy)[ok] / np.hypot(ux, uy)[ok]
    assert rel.max() < 0.01
    m = ctx.metrics["imu_truth"]
    assert m["bins"]["valid"] >= 7 and m["checks"]["axes"]["y"]["sign"] == "agrees"


def test_imu_truth_with_noise_and_the_bias_from_the_still_start():
    src, ctx, packets = scene_packets(imu_gyro_noise_dps=0.1, imu_gyro_bias_dps=(1.0, -0.5, 0.3))
    g = ctx.geometry
    (x, y, t, ux, uy, gx, gy), ctx = through_imu_truth(
        packets, ctx, focal_px=g.f, principal_point_px=(g.cx, g.cy), time_offset_us=0,
        calibration_us=1_200_000)
    c = ctx.metrics["imu_truth"]["camera"]
    assert c["gyro_bias_from"].startswith("still stretch: 2 x 200 ms from 0.000 s")
    np.testing.assert_allclose(c["gyro_bias_dps"], [1.0, -0.5, 0.3], atol=0.02)
    ok = np.isfinite(gx)
    rel = np.hypot(gx - ux, gy - uy)[ok] / np.hypot(ux, uy)[ok]
    assert ok.mean() > 0.8 and np.median(rel) < 0.01 and np.percentile(rel, 99) < 0.05


def test_scores_against_the_simulated_gyro_and_against_the_exact_flow(tmp_path):
    """The same chain scored against imu_truth (bias from the still start, principal point and
    time offset estimated, gyro noise) and against the renderer's exact flow: AEE within 5 %."""
    import json
    from pathlib import Path

    from evchain.cli import main

    pipeline = Path(__file__).resolve().parents[2] / "pipelines" / "rotation-imu-lk.yaml"
    text = pipeline.read_text()
    exact = tmp_path / "exact.yaml"
    exact.write_text(text.replace("  - use: imu_truth\n    calibration_us: 1500000\n", "")
                     .replace("  - use: imu_rate_plot\n", ""))
    aee = {}
    for name, path in (("gyro", pipeline), ("exact", exact)):
        assert main(["run", str(path), "--out", str(tmp_path / name)]) == 0
        report = json.loads((tmp_path / name / "report.json").read_text())
        aee[name] = report["metrics"]["flow"]["aee_pxs"]
    assert "imu_truth" in json.loads((tmp_path / "gyro" / "report.json").read_text())["metrics"]
    assert abs(aee["gyro"] / aee["exact"] - 1) < 0.05
