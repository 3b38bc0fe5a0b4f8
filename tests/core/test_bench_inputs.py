"""The benchmark inputs of the reference drive are made with the pipelines' parameters, and the
rows that say they use a pipeline's parameters do (small fake drives; nothing is rendered)."""

import numpy as np
import pytest

from evchain.bench import cut_every
from evchain.benchmarks import foe_ttc
from evchain.benchmarks.drive_inputs import (
    FLOW_COLUMNS,
    PIPELINES,
    drive_events,
    drive_flow,
    load_events,
    load_flow,
)
from evchain.benchmarks.plane_flow import expanding_scene_events
from evchain.core.config import load_pipeline
from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.registry import make_registry
from evchain.testing.synthetic import approach_flow_packets

LK = PIPELINES / "reference-lk.yaml"
PLANE = PIPELINES / "reference-plane.yaml"


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("EVCHAIN_CACHE", str(tmp_path / "cache"))


def _edited(tmp_path, source, old: str, new: str):
    text = source.read_text()
    assert text.count(old) == 1
    path = tmp_path / source.name
    path.write_text(text.replace(old, new))
    return path


def _stage(path, use):
    return load_pipeline(path, make_registry()).stage(use)


def test_a_changed_pipeline_parameter_is_another_entry(tmp_path):
    window = _edited(tmp_path, LK, "  - use: lk_flow\n", "  - use: lk_flow\n    window_us: 60000\n")
    assert drive_flow(window, 220, 1).key != drive_flow(LK, 220, 1).key
    assert drive_flow(window, 220, 1).params["flow"]["window_us"] == 60000
    assert drive_events(window, 220, 1).key == drive_events(LK, 220, 1).key  # same drive
    assert drive_flow(LK, 220, 2).key != drive_flow(LK, 220, 1).key          # another stretch
    threshold = _edited(tmp_path, PLANE, "threshold_on: 20", "threshold_on: 21")
    assert drive_events(threshold, 220, 1).key != drive_events(PLANE, 220, 1).key
    assert drive_flow(threshold, 220, 1).key != drive_flow(PLANE, 220, 1).key
    # the render threads do not change the frames: reference.yaml (threads 0) shares the drive
    assert drive_events(PIPELINES / "reference.yaml", 0, 2).key == drive_events(LK, 0, 2).key


@pytest.mark.parametrize("path, use", [(LK, "lk_flow"), (PLANE, "plane_flow")])
def test_the_flow_input_is_read_from_the_pipeline(tmp_path, path, use):
    inp = drive_flow(path, 220, 1)
    assert inp.params["use"] == use
    assert inp.params["flow"] == _stage(path, use).params.model_dump(mode="json")
    # a setting in the pipeline's flow stage (the reference pipelines run the defaults) is read
    edited = _edited(tmp_path, path, f"  - use: {use}\n", f"  - use: {use}\n    window_us: 70000\n")
    assert drive_flow(edited, 220, 1).params["flow"]["window_us"] == 70_000
    assert inp.params["flow"]["window_us"] is None
    events = inp.needs[0]
    assert events.params["emulator"] == _stage(path, "emulator").params.model_dump(mode="json")
    scene = _stage(path, "scene").params.model_dump(mode="json")
    del scene["threads"]
    assert events.params["scene"] == {**scene, "start_m": 220.0, "duration_s": 1.0}


def _fake_events(path, start_m, seconds, n_segments=300):
    """Store an expanding scene as the drive events of ``path``'s stretch (no rendering)."""
    inp = drive_events(path, start_m, seconds)
    ev, _ = expanding_scene_events(seconds, Geometry(320, 240), foe=(160.0, 120.0),
                                   t_collision_s=2.0, n_segments=n_segments)
    packets = cut_every(ev)
    inp.path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(inp.path, x=ev.x, y=ev.y, t=ev.t, p=ev.p,
             bounds=np.array([p.t_start for p in packets] + [packets[-1].t_end]))
    return inp


def _columns(packets, cols=("x", "y", "t", "vx", "vy")):
    return [np.concatenate([getattr(p, c) for p in packets]) for c in cols]


@pytest.mark.parametrize("path, use", [(LK, "lk_flow"), (PLANE, "plane_flow")])
def test_the_cached_flow_is_the_pipeline_stage_on_the_cached_events(path, use):
    events = _fake_events(path, 220, 0.2)
    inp = drive_flow(path, 220, 0.2)
    assert inp.prepare(echo=lambda s: None)
    got, ctx = load_flow(inp)
    assert ctx.geometry.width == 320 and ctx.truth is not None

    packets, ctx = load_events(events)
    st = _stage(path, use)
    f = st.cls()
    f.setup(st.params, Context(geometry=ctx.geometry, truth=ctx.truth))
    want = [f.process(p) for p in packets]
    last = f.flush()
    want += [last] if last is not None else []
    assert len(_columns(got)[0]) > 1000
    for a, b in zip(_columns(got), _columns(want), strict=True):
        assert np.array_equal(a, b)


def _fake_flow(path, quick, overrides=()):
    """Store expansion flow (FOE at the image centre) as the flow input of the quick stretch."""
    inp = drive_flow(path, *foe_ttc.stretch(quick), overrides)
    packets = approach_flow_packets(foe=(159.5, 119.5), tau_s=5.0, n=20_000,
                                    geometry=Geometry(320, 240), duration_us=1_000_000,
                                    n_packets=100, normal_only=True)
    flow = FlowPacket.concat(packets)
    inp.path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(inp.path, **{c: getattr(flow, c) for c in FLOW_COLUMNS},
             bounds=np.array([p.t_start for p in packets] + [packets[-1].t_end]))
    return inp


def _spy(monkeypatch, uses):
    """Record the parameters every filter in ``uses`` is set up with."""
    registry = make_registry()
    seen: dict[str, list] = {}
    for use in uses:
        cls = registry.get(use)
        orig = cls.setup

        def setup(self, params, context, orig=orig, use=use):
            seen.setdefault(use, []).append(params)
            return orig(self, params, context)

        monkeypatch.setattr(cls, "setup", setup)
    return seen


def test_the_foe_rows_use_the_pipeline(monkeypatch):
    inp = _fake_flow(LK, quick=True)
    seen = _spy(monkeypatch, ["foe_map", "foe_fit"])
    [row] = foe_ttc.WORKLOADS["foe-map-pipeline-lk"](True)
    assert row.params_from == "pipelines/reference-lk.yaml" and inp.key in row.data
    want = _stage(LK, "foe_map").params
    assert seen["foe_map"] and all(p == want for p in seen["foe_map"])
    assert row.extra["params"] == {"foe_map": want.model_dump(mode="json")}

    seen.clear()
    [row] = foe_ttc.WORKLOADS["foe-fit-pipeline-lk"](True)
    assert row.params_from == "pipelines/reference-lk.yaml" and inp.key in row.data
    for use in ("foe_map", "foe_fit"):
        assert seen[use] and all(p == _stage(LK, use).params for p in seen[use])
        assert row.extra["params"][use] == _stage(LK, use).params.model_dump(mode="json")

    seen.clear()
    [row] = foe_ttc.WORKLOADS["foe-map-reference-lk"](True)   # the row's settings, and says so
    assert "foe_map with 1 ms reads and 300 ms decay" in row.data and inp.key in row.data
    assert all(p == type(p)(**foe_ttc.ROW_SETTINGS) for p in seen["foe_map"])


def test_the_pitch_rows_fit_the_rotation_and_take_the_gyro_on_the_same_flow(monkeypatch):
    """``foe-fit-pitch-lk``: two rows on one input, the pitching drive's flow with the scene's
    IMU attached on loading; the gyro row's rotation is the gyro's (within its noise of the
    truth), the other row fits it."""
    inp = _fake_flow(LK, True, foe_ttc.PITCH)
    assert inp.key != drive_flow(LK, *foe_ttc.stretch(True)).key
    packets, ctx = load_flow(inp)
    imu = np.concatenate([p.series["imu"] for p in packets])
    assert np.array_equal(imu["t"], np.arange(packets[0].t_start, packets[-1].t_end, 1000))
    seen = _spy(monkeypatch, ["foe_fit"])
    fit, gyro = foe_ttc.WORKLOADS["foe-fit-pitch-lk"](True)
    assert (fit.workload, gyro.workload) == ("foe-fit-pitch-lk", "foe-fit-pitch-gyro-lk")
    assert inp.key in fit.data and inp.key in gyro.data
    assert {p.rotation_source for p in seen["foe_fit"]} == {"flow", "imu"}
    assert gyro.extra["params"]["foe_fit"]["rotation_source"] == "imu"
    assert gyro.extra["rotation_rate_error_deg_s"] < 0.5


def test_the_chain_row_runs_the_pipeline_stages(monkeypatch):
    inp = _fake_events(LK, *foe_ttc.stretch(True), n_segments=200)
    timed = ["lk_flow", "foe_map", "foe_fit", "ttc"]
    seen = _spy(monkeypatch, timed)
    rows = foe_ttc.WORKLOADS["chain-reference-lk"](True)
    # one thread and stage threads, side by side on the same input with the same stages
    assert [r.workload for r in rows] == ["chain-reference-lk", "chain-reference-lk-threads"]
    assert [r.extra["threads"] for r in rows] == ["one", "stage threads"]
    assert rows[0].error == rows[1].error  # the scorer's run, once for both
    for row in rows:
        assert row.params_from == "pipelines/reference-lk.yaml" and row.data == inp.describe()
        assert row.stage == "+".join(timed)
        for use in timed:
            want = _stage(LK, use).params
            assert seen[use] and all(p == want for p in seen[use]), use
            assert row.extra["params"][use] == want.model_dump(mode="json")
