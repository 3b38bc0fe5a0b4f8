"""``scene_events`` replays a simulator run's events with the same exact ground truth."""

import numpy as np
import pytest

import evchain
from evchain.core.packets import EventPacket
from evchain.errors import DataError
from evchain.filters.scene_events import SceneEvents
from evchain.testing.contract import check_source, run_source

SCENE = {"scenario": "high-rise", "width": 64, "height": 48, "supersample": 1,
         "start_m": 200.0, "duration_s": 0.06}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A short drive's events written by scene -> emulator -> aedat_writer."""
    out = tmp_path_factory.mktemp("drive")
    scene = "\n".join(f"    {k}: {v}" for k, v in SCENE.items())
    (out / "drive.yaml").write_text(f"""chain:
  - use: scene
{scene}
  - use: emulator
  - use: aedat_writer
    path: events.aedat
""")
    report = evchain.run(out / "drive.yaml", out_dir=out / "run")
    assert report["filters"][1]["events_out"] > 1000  # a real drive, not an empty file
    return out / "run" / "events.aedat"


def test_same_events_and_truth_as_the_scene(recorded, tmp_path):
    from evchain.filters.scene import SceneSource
    from evchain.io.aedat2 import AedatSource

    packets, ctx = run_source(SceneEvents, {**SCENE, "path": str(recorded)}, tmp_path)
    plain, _ = run_source(AedatSource, {"path": str(recorded)}, tmp_path)
    got, want = EventPacket.concat(packets), EventPacket.concat(plain)
    for c in EventPacket.columns:
        assert np.array_equal(getattr(got, c), getattr(want, c)), c
    scene = SceneSource()
    scene.id = "scene"
    scene_ctx = type(ctx)(out_dir=tmp_path)
    scene.setup(SceneSource.Params(**SCENE), scene_ctx)
    assert ctx.geometry == scene_ctx.geometry and ctx.geometry.f > 0
    x, y, t = got.x.astype(float), got.y.astype(float), got.t.astype(float)
    for a, b in zip(ctx.truth.flow(x, y, t), scene_ctx.truth.flow(x, y, t), strict=True):
        assert np.array_equal(a, b, equal_nan=True) and np.isfinite(a).mean() > 0.9
    assert np.array_equal(ctx.truth.ttc(t), scene_ctx.truth.ttc(t), equal_nan=True)


def test_contract(recorded, tmp_path):
    check_source(SceneEvents, {**SCENE, "path": str(recorded)}, out_dir=tmp_path, max_packets=5)


def test_other_sensor_size_is_a_clear_error(recorded, tmp_path):
    with pytest.raises(DataError, match=r"events\.aedat: the sensor is 64x48 but the scene's "
                                        r"camera is 320x240"):
        run_source(SceneEvents, {**SCENE, "width": 320, "height": 240, "path": str(recorded)},
                   tmp_path)


def _flow_pipeline(path, **emulator):
    scene = "\n".join(f"    {k}: {v}" for k, v in SCENE.items())
    extra = "\n".join(f"    {k}: {v}" for k, v in emulator.items())
    path.write_text(f"chain:\n  - use: scene\n{scene}\n  - use: emulator\n{extra}\n"
                    "  - use: lk_flow\n  - use: flow_scorer\n")
    return path


def test_replay_gives_the_rendered_runs_numbers(recorded, tmp_path):
    """``run --replay``: the flow metrics equal those of rendering and emulating again."""
    from evchain.cli import main

    pipeline = _flow_pipeline(tmp_path / "flow.yaml")
    direct = evchain.run(pipeline, out_dir=tmp_path / "direct")
    assert main(["run", str(pipeline), "--replay", str(recorded), "--out",
                 str(tmp_path / "replayed"), "--no-progress"]) == 0
    import json

    replayed = json.loads((tmp_path / "replayed" / "report.json").read_text())
    assert replayed["pipeline"]["chain"][0]["use"] == "scene_events"
    assert direct["metrics"]["flow"]["n_flow"] > 100
    assert replayed["metrics"]["flow"] == direct["metrics"]["flow"]


def test_replay_refuses_a_run_of_other_parameters(recorded, tmp_path):
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry
    from evchain.errors import ConfigError
    from evchain.filters.scene_events import replay_spec

    spec = load_pipeline(_flow_pipeline(tmp_path / "f.yaml", threshold_on=0.3),
                         make_registry())
    with pytest.raises(ConfigError, match=r"not this pipeline's emulator: threshold_on: "
                                          r"0\.2 there, 0\.3 here"):
        replay_spec(spec, recorded)


def test_sweep_over_a_recorded_drive(recorded, tmp_path):
    """``replay:`` in a sweep: every variation reads the recording; varying the emulator, which
    a recording cannot follow, is refused before anything runs."""
    from evchain.errors import ConfigError
    from evchain.sweep import load_sweep, run_sweep

    _flow_pipeline(tmp_path / "flow.yaml")
    sweep_file = tmp_path / "s.yaml"
    sweep_file.write_text(f"base: flow.yaml\nreplay: {recorded}\n"
                          "vary:\n  lk_flow.refractory_us: [0, 100000]\n"
                          "report: [flow.n_flow]\n")
    rows = run_sweep(load_sweep(sweep_file), tmp_path / "out", workers=1, echo=lambda _: None)
    assert rows[0]["flow.n_flow"] > rows[1]["flow.n_flow"] > 0  # refractory thins the flow
    sweep_file.write_text(f"base: flow.yaml\nreplay: {recorded}\n"
                          "vary:\n  emulator.threshold_on: [0.2, 0.3]\n")
    with pytest.raises(ConfigError, match="not this pipeline's emulator: threshold_on"):
        run_sweep(load_sweep(sweep_file), tmp_path / "out2", workers=1, echo=lambda _: None)
    assert not (tmp_path / "out2").exists()


def test_replay_takes_a_parameter_the_recording_predates_as_its_default(recorded, tmp_path):
    """A recording made before a scene parameter existed (its resolved pipeline does not name
    it) replays under that parameter's default, and is refused under any other value."""
    import shutil

    import yaml

    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry
    from evchain.errors import ConfigError
    from evchain.filters.scene_events import replay_spec

    old = tmp_path / "old"
    shutil.copytree(recorded.parent, old)
    resolved = old / "pipeline.resolved.yaml"
    doc = yaml.safe_load(resolved.read_text())
    del doc["chain"][0]["contrast"]
    resolved.write_text(yaml.safe_dump(doc))
    registry = make_registry()
    spec = load_pipeline(_flow_pipeline(tmp_path / "f.yaml"), registry)
    assert replay_spec(spec, old / "events.aedat").stages[0].use == "scene_events"
    spec = load_pipeline(_flow_pipeline(tmp_path / "f.yaml"), registry, ["scene.contrast=0.5"])
    with pytest.raises(ConfigError, match=r"contrast: None there, 0\.5 here"):
        replay_spec(spec, old / "events.aedat")


def test_replay_adds_the_simulated_imu(recorded, tmp_path):
    """A replay with imu_rate_hz carries the series imu over the drive: the scene's true
    readings at the same times (the recording was made without an IMU: the IMU does not
    change the events, so the replay accepts it); without noise, the scene's samples."""
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry
    from evchain.filters.scene import SceneSource
    from evchain.filters.scene_events import replay_spec

    packets, _ = run_source(SceneEvents, {**SCENE, "path": str(recorded), "imu_rate_hz": 500},
                            tmp_path)
    imu = np.concatenate([p.series["imu"] for p in packets])
    assert len(imu) >= 25 and np.all(np.diff(imu["t"]) == 2000)
    frames, _ = run_source(SceneSource, {**SCENE, "imu_rate_hz": 500}, tmp_path)
    want = np.concatenate([p.series["imu"] for p in frames])
    common = np.isin(want["t"], imu["t"])
    assert common.sum() == len(imu)
    assert np.array_equal(want[common], imu)
    spec = load_pipeline(_flow_pipeline(tmp_path / "f.yaml"), make_registry(),
                         ["scene.imu_rate_hz=1000", "scene.imu_gyro_noise_dps=0.1"])
    first = replay_spec(spec, recorded).stages[0]
    assert first.use == "scene_events" and first.params.imu_rate_hz == 1000
    assert first.params.imu_gyro_noise_dps == 0.1


def test_a_replay_with_the_recordings_scene_id_has_its_imu_noise(recorded, tmp_path):
    """The IMU noise is seeded by the stage id (``<id>.imu``), as the scene source's: a
    replay under the recording's scene id draws the same noisy samples, under another id
    other ones; ``--replay`` keeps the scene stage's id."""
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry
    from evchain.filters.scene import SceneSource
    from evchain.filters.scene_events import replay_spec

    noisy = {**SCENE, "imu_rate_hz": 500, "imu_gyro_noise_dps": 0.5, "imu_accel_noise_g": 0.01}

    def imu(cls, stage_id, **more):
        packets, _ = run_source(cls, {**noisy, **more}, tmp_path, stage_id=stage_id)
        return np.concatenate([p.series["imu"] for p in packets])

    want = imu(SceneSource, "cam")
    same = imu(SceneEvents, "cam", path=str(recorded))
    other = imu(SceneEvents, "scene", path=str(recorded))
    common = np.isin(want["t"], same["t"])
    assert common.sum() == len(same) >= 25
    assert np.array_equal(want[common], same)
    assert not np.array_equal(want[common], other)
    pipeline = _flow_pipeline(tmp_path / "f.yaml")
    spec = load_pipeline(pipeline, make_registry())
    assert replay_spec(spec, recorded).stages[0].id == spec.stages[0].id
