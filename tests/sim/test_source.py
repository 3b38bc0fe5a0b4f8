"""The ``scene`` source and ``scene_preview`` sink: contract, time sampling, errors, pipelines."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evchain.core.config import pipeline_from_text
from evchain.core.registry import make_registry
from evchain.errors import ConfigError
from evchain.filters.scene import SceneSource
from evchain.sim.config import SceneConfig, make_config
from evchain.sim.drive import Scene
from evchain.testing.contract import check_source, make_context

SMALL = dict(width=48, height=36, supersample=1, start_m=200.0, duration_s=0.03)
PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"


def test_contract_and_truth_in_context():
    packets = check_source(SceneSource, dict(SMALL, packet_us=7000, max_frames_per_packet=3))
    assert packets[0].geometry.f == pytest.approx(18 / np.tan(np.radians(17.5)))
    times = np.concatenate([p.t for p in packets])
    assert times[0] == 0 and np.all(np.diff(times) > 0) and times[-1] < 30_000


def _frames(params):
    f = SceneSource()
    ctx = make_context(None)
    f.setup(SceneSource.Params(**params), ctx)
    packets = list(f.packets())
    return f, ctx, packets


def test_adaptive_step_bounds_image_motion():
    f, ctx, packets = _frames(dict(SMALL, max_motion_px=0.3, dt_max_us=50_000))
    t = np.concatenate([p.t for p in packets])
    assert packets[-1].t_end == 30_000 and len(t) > 3
    ys, xs = np.mgrid[0:36, 0:48].astype(float)
    for t0, t1 in zip(t[:-1], t[1:], strict=True):
        vx, vy = ctx.truth.flow(xs, ys, float(t0))
        assert np.hypot(vx, vy).max() * (t1 - t0) * 1e-6 <= 0.3 + 1e-9
    # a faster camera gets shorter steps
    _, _, fast = _frames(dict(SMALL, max_motion_px=0.3, speed_mps=40.0, duration_s=0.015))
    assert np.diff(fast[0].t).mean() < np.diff(t).mean()
    assert ctx.metrics["scene"]["frames"] == len(t)


def test_fixed_step_and_determinism():
    _, _, a = _frames(dict(SMALL, dt_us=2000))
    _, _, b = _frames(dict(SMALL, dt_us=2000))
    ta = np.concatenate([p.t for p in a])
    np.testing.assert_array_equal(ta, np.arange(0, 30_000, 2000))
    for p, q in zip(a, b, strict=True):
        np.testing.assert_array_equal(p.frames, q.frames)
    s1 = Scene.from_params(scenario="curves", dynamics="curves", width=40, height=30)
    s2 = Scene.from_params(scenario="curves", dynamics="curves", width=40, height=30)
    np.testing.assert_array_equal(s1.boxes, s2.boxes)
    np.testing.assert_array_equal(s1.render(3.0)[0], s2.render(3.0)[0])


def test_render_ahead_thread_gives_the_same_packets():
    """threads != 1 renders packets ahead in a background thread: same packets, same metrics;
    a consumer that stops early stops the thread."""
    params = dict(SMALL, packet_us=5000, max_frames_per_packet=4)
    _, ca, a = _frames(params)
    _, cb, b = _frames(dict(params, threads=2))
    assert len(a) == len(b) > 3
    for p, q in zip(a, b, strict=True):
        assert (p.t_start, p.t_end) == (q.t_start, q.t_end)
        np.testing.assert_array_equal(p.t, q.t)
        np.testing.assert_array_equal(p.frames, q.frames)
    assert ca.metrics["scene"] == cb.metrics["scene"]
    import threading

    f = SceneSource()
    f.setup(SceneSource.Params(**dict(params, threads=2)), make_context(None))
    gen = f.packets()
    next(gen)
    gen.close()
    assert not any(t.name == "scene-render-ahead" for t in threading.enumerate())


@pytest.mark.parametrize("values,needle", [
    (dict(fov_deg=0.0), "fov_deg"),
    (dict(fov_deg=180.0), "fov_deg"),
    (dict(width=0), "width"),
    (dict(height=0), "height"),
    (dict(speed_mps=-1.0), "speed_mps"),
    (dict(duration_s=20.0), "shorter than the drive"),
    (dict(scenario="open-field", start_m=50.0, duration_s=2.0), "shorter than the drive"),
    (dict(scenario="curves"), "dynamics: curves"),
    (dict(dynamics="curves"), "needs scenario 'curves'"),
    (dict(speed_mps=0.0), "explicit duration_s"),
    (dict(scenario="mountains"), "scenario"),
])
def test_bad_parameters_are_clear(values, needle):
    with pytest.raises(ConfigError, match=needle):
        make_config(SceneConfig, **values)


def test_bad_parameters_in_a_pipeline():
    text = "name: x\nchain:\n  - use: scene\n    fov_deg: 190\n"
    with pytest.raises(ConfigError, match="fov_deg"):
        pipeline_from_text(text, "x.yaml", make_registry())
    text = "name: x\nchain:\n  - use: scene\n    dt_min_us: 100\n    dt_max_us: 10\n"
    with pytest.raises(ConfigError, match="dt_min_us"):
        pipeline_from_text(text, "x.yaml", make_registry())


def test_preview_sink_writes_pngs(tmp_path):
    import imageio.v3 as iio

    from evchain.filters.scene_preview import ScenePreview

    src, ctx, packets = _frames(dict(SMALL, dt_us=5000))
    ctx.out_dir = tmp_path
    sink = ScenePreview()
    sink.setup(ScenePreview.Params(times_s=[0.0, 0.012], scenarios=["open-field"]), ctx)
    for p in packets:
        assert sink.process(p) is p
    sink.flush()
    names = sorted(q.name for q in (tmp_path / "preview").iterdir())
    assert len(names) == 12 and "high-rise_t000012ms_flow.png" in names
    img = iio.imread(tmp_path / "preview" / "high-rise_t000012ms_frame.png")
    assert img.shape == (36, 48) and img.std() > 5
    flow = iio.imread(tmp_path / "preview" / "open-field_t000000ms_flow.png")
    assert flow.shape == (36, 48, 3)


@pytest.mark.parametrize("name", ["scene-preview.yaml", "reference.yaml"])
def test_pipelines_validate(name):
    registry = make_registry()
    path = PIPELINES / name
    try:
        spec = pipeline_from_text(path.read_text(), str(path), registry)
    except ConfigError as exc:
        if "unknown filter" in str(exc) and ("emulator" in str(exc) or "aedat" in str(exc)):
            pytest.skip(f"filter of another stage missing: {exc}")
        raise
    assert spec.stages[0].use == "scene"


def test_scene_preview_pipeline_runs(tmp_path):
    from evchain.core.chain import run_pipeline

    registry = make_registry()
    path = PIPELINES / "scene-preview.yaml"
    text = path.read_text()
    spec = pipeline_from_text(text, str(path), registry,
                              overrides=["scene.width=40", "scene.height=30"])
    result = run_pipeline(spec, registry, tmp_path)
    assert result.report["status"] == "ok"
    files = list((tmp_path / "preview").glob("*.png"))
    assert {f.name.split("_t")[0] for f in files} == {"high-rise", "high-rise-orange",
                                                      "open-field", "curves"}


@pytest.mark.parametrize("threads", [2, 3])
def test_speculative_frames_match_one_thread(threads):
    """Scene.frames with threads renders frames ahead at the last step and drops them when the
    step changes: same times and bit-identical frames as one thread, for steps that stay, change
    once, alternate, and run past the end."""
    steps = [400, 400, 400, 400, 900, 900, 400, 900, 400, 400, 400, 250, 250, 250, 250, 250]

    def run(n):
        sc = Scene.from_params(threads=n, width=40, height=30, start_m=250.0, duration_s=0.5)
        alone = sc._render_alone
        ahead = []
        sc._render_alone = lambda t_s: ahead.append(t_s) or alone(t_s)   # frames started ahead
        calls = []

        def step(vmax):
            assert vmax > 0
            calls.append(steps[len(calls) % len(steps)])
            return calls[-1]

        return list(sc.frames(1000, 9000, step)), calls, ahead

    one, calls1, _ = run(1)
    many, calls, ahead = run(threads)
    assert len(ahead) > 5 and calls == calls1 and len(one) == len(many) == len(calls) > len(steps)
    assert [t for t, _, _ in one] == list(np.cumsum([1000] + calls[:-1]))
    for (ta, fa, va), (tb, fb, vb) in zip(one, many, strict=True):
        assert ta == tb and va == vb
        np.testing.assert_array_equal(fa, fb)


def test_contrast_scales_log_intensity_and_zero_is_uniform_grey():
    full = Scene.from_params(**SMALL)
    half = Scene.from_params(**SMALL, contrast=0.5)
    grey = Scene.from_params(**SMALL, contrast=0.0)
    a, va = full.render(0.01)
    b, vb = half.render(0.01)
    g, vg = grey.render(0.01)
    assert np.ptp(a) > 0.1     # the scene has structure
    np.testing.assert_allclose(np.log(b / 0.5), 0.5 * np.log(a / 0.5), rtol=1e-5, atol=1e-6)
    assert np.all(g == np.float32(0.5))
    # the motion (adaptive step) and the ground truth are the scene's
    assert va == vb == vg
    from evchain.sim.truth import SceneTruth

    t = np.array([0.0, 15_000.0])
    np.testing.assert_array_equal(SceneTruth(grey).ttc(t), SceneTruth(full).ttc(t))
