"""The rows of sensor_noise, aps, frame_flow, foe_lines and imu_rate_plot run at a tiny size and
give a finite throughput next to a finite error (no timing is checked: speed is measured by
``evchain bench``)."""

import math

import numpy as np
import pytest

from evchain.bench import cut_every
from evchain.benchmarks import frames, imu_truth, sensor_noise
from evchain.benchmarks.drive_inputs import PIPELINES, drive_aps, drive_events, drive_flow
from evchain.benchmarks.plane_flow import expanding_scene_events
from evchain.core.packets import Geometry
from evchain.core.series import IMU
from evchain.testing.synthetic import RollingCamera

STRETCH = (220.0, 0.4)


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("EVCHAIN_CACHE", str(tmp_path / "cache"))


@pytest.fixture
def tiny_frames(tmp_path):
    """pipelines/frames-reference.yaml at 64x48."""
    text = (PIPELINES / "frames-reference.yaml").read_text()
    assert text.count("width: 320") == 1 and text.count("height: 240") == 1
    path = tmp_path / "frames-tiny.yaml"
    path.write_text(text.replace("width: 320", "width: 64").replace("height: 240", "height: 48"))
    return path


def _finite(row):
    assert math.isfinite(row.throughput) and row.throughput > 0, row
    assert row.error is not None and math.isfinite(row.error), row
    assert row.data and row.params_from


def test_aps_rows(tiny_frames):
    ideal, davis = frames.aps_rows(tiny_frames, 220.0, 0.1, samples=8)
    assert (ideal.workload, davis.workload) == ("aps-reference", "aps-reference-davis240")
    for row in (ideal, davis):
        _finite(row)
        assert row.extra["frames"] >= 2 and row.extra["input_frames"] > row.extra["frames"]
    # ideal 8-bit frames: quantisation alone has 0.29 DN rms; the exposure integral between
    # renders adds little to it
    assert ideal.extra["noise_floor_dn"] == pytest.approx(1 / math.sqrt(12))
    assert ideal.error < 4 * ideal.extra["noise_floor_dn"]
    # shot and read noise dominate the DAVIS240's error, as the model says
    assert 0.8 < davis.extra["error_over_floor"] < 1.3


def test_frame_flow_and_foe_lines_rows(tiny_frames):
    inp = drive_flow(tiny_frames, *STRETCH)
    assert inp.needs[0].key == drive_aps(tiny_frames, *STRETCH).key
    assert inp.prepare(echo=lambda s: None)
    [flow] = frames.frame_flow_rows(tiny_frames, *STRETCH)
    _finite(flow)
    assert flow.extra["flow_fields"] >= 5 and flow.extra["n_scored"] > 0
    [foe] = frames.foe_lines_rows(tiny_frames, *STRETCH)
    _finite(foe)
    assert foe.extra["scored"] > 0 and math.isfinite(foe.extra["foe_dy_mean_px"])
    assert inp.key in foe.data


def test_the_frame_rows_need_their_inputs_prepared():
    from evchain.bench import missing_inputs

    missing = missing_inputs({k: frames.WORKLOADS[k] for k in ("frame-flow-reference",
                                                              "foe-lines-reference")}, True)
    assert [i.kind for i in missing["frame-flow-reference"]] == ["drive-aps"]
    assert [i.kind for i in missing["foe-lines-reference"]] == ["drive-flow"]


def _fake_drive_events(seconds):
    """An expanding scene stored as the drive events of pipelines/reference.yaml (no
    rendering)."""
    inp = drive_events(PIPELINES / "reference.yaml", 220.0, seconds)
    ev, _ = expanding_scene_events(seconds, Geometry(320, 240), foe=(160.0, 120.0),
                                   t_collision_s=2.0, n_segments=100)
    packets = cut_every(ev)
    inp.path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(inp.path, x=ev.x, y=ev.y, t=ev.t, p=ev.p,
             bounds=np.array([p.t_start for p in packets] + [packets[-1].t_end]))
    return inp


def test_sensor_noise_row():
    [row] = sensor_noise.noise_rows(_fake_drive_events(0.3), repeat=1)
    _finite(row)
    assert row.limit_ratio is not None and row.limit_ratio > 0
    # the measured background activity is the configured one within its sampling spread
    assert row.error < 5 * row.extra["ba_rate_sampling_rel_sd"] + 0.01
    assert row.extra["hot_pixels_as_chosen"]
    assert row.extra["hot_pixel_share"] == row.extra["hot_pixel_share_configured"]
    assert row.extra["noise_events"] > 0


def test_sensor_noise_row_counts_only_the_noise():
    """Without shot noise and hot pixels, the background activity is the leak alone."""
    inp = _fake_drive_events(0.3)
    [row] = sensor_noise.noise_rows(inp, repeat=1, noise={
        "leak_rate_hz": 5.0, "shot_rate_hz": 0.0, "hot_pixel_fraction": 0.0,
        "hot_pixel_rate_hz": 1000.0})
    assert row.extra["ba_rate_configured_hz"] == 5.0
    assert row.error < 0.02 and row.extra["ba_on_share"] == 1.0
    assert row.extra["hot_pixel_share"] == 0.0


def test_plot_imu_rate_row():
    cam = RollingCamera(Geometry(80, 60), centre=(44.0, 27.0), w0=0.5, amp=0.15,
                        period_s=1.0, duration_us=1_500_000)
    ev = cam.events().with_series(IMU.name, cam.imu(bias_dps=imu_truth.SIM_BIAS))
    [row] = imu_truth.plot_rows(cut_every(ev), {"gyro_bias_dps": imu_truth.SIM_BIAS,
                                                "calibration_us": 500_000}, "tiny", repeat=1)
    assert math.isfinite(row.throughput) and row.throughput > 0
    assert row.error is None and row.error_name.startswith("none")  # a plot estimates nothing
    assert row.extra["bins"] > 0 and row.extra["png_bytes"] > 1000


def test_workloads_run_with_blas_on_one_thread():
    """BLAS's idle worker threads spin and CPU time counts them: `bench.run` limits BLAS to one
    thread while the workloads run, and gives the previous limits back afterwards."""
    from threadpoolctl import threadpool_info

    from evchain import bench

    def blas_threads():
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    np.dot(np.ones((64, 64)), np.ones((64, 64)))      # numpy's BLAS is loaded
    before = blas_threads()
    seen = []

    def workload(quick):
        seen.extend(blas_threads())
        return [bench.BenchRow("probe", "none", 1.0, "calls/s", data="nothing")]

    bench.run({"probe": workload}, echo=lambda s: None)
    assert seen and set(seen) == {1}
    assert blas_threads() == before


def test_event_scorer_row_finds_the_bin_without_events():
    """``scorer-events``: the one 100 ms bin without events sets the reported
    ``obstacle_events_since_s`` (1.9 s) and leaves 29 of the window's 30 bins covered."""
    from evchain.benchmarks import scorers

    [row] = scorers.WORKLOADS["scorer-events"](True)
    assert row.error == pytest.approx(0.0, abs=1e-9) and row.throughput > 0
    assert row.extra["obstacle_events_coverage"] == pytest.approx(29 / 30)


def test_tiled_frames_give_each_pixel_the_base_pixels_input():
    from evchain.benchmarks.emulator import textured_scene, tiled
    base, _ = textured_scene(3, 200.0)
    big = tiled(base, 1280, 720)
    assert big.shape == (3, 720, 1280) and big.flags.c_contiguous
    y, x = np.mgrid[0:720, 0:1280]
    np.testing.assert_array_equal(big, base[:, y % 240, x % 320])
