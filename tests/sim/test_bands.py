"""The scene's row bands (``band_rows``): kernels against tests/naive, the schedule's rules and
the events against frames rendered whole."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.filters.scene import SceneSource
from evchain.kernels.scene_bands import StepRule, interpolate_band, predict, rows_of, step_us
from evchain.kernels.scene_render import render_row_set
from evchain.sim.bands import AHEAD, MAX_PAUSE, BandFrames, _Ahead
from evchain.sim.drive import Scene
from evchain.testing.contract import make_context
from tests.naive import scene_bands as NB
from tests.naive import scene_kernels as N

SMALL = dict(width=40, height=30, supersample=2, start_m=200.0)


def _interp_case(rng, cap, h, w, r0, r1, nslots):
    ring = rng.uniform(0, 3, (cap, h, w)).astype(np.float32)
    start = rng.uniform(0, 3, (h, w)).astype(np.float32)
    end_slot = int(rng.integers(cap))
    others = np.setdiff1d(np.arange(cap), [end_slot])
    slots = rng.choice(others, size=min(nslots, len(others)), replace=False).astype(np.int64)
    t0 = int(rng.integers(0, 1000))
    t1 = t0 + int(rng.integers(2, 5000))
    times = np.sort(rng.integers(t0 + 1, t1, len(slots))).astype(np.int64)
    return ring, slots, times, start, t0, t1, end_slot


def test_interpolate_band_vs_naive_random_and_edges():
    rng = np.random.default_rng(5)
    cases = [(8, 30, 40, 16, 30, 5),      # the last band of an image not divisible by 16
             (8, 30, 40, 0, 16, 7),       # the first band
             (3, 5, 7, 4, 5, 2),          # one row
             (4, 6, 9, 2, 2, 3),          # no row
             (5, 6, 9, 0, 6, 0)]          # no frame between
    for _ in range(20):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 50))
        r0 = int(rng.integers(0, h))
        cases.append((int(rng.integers(2, 12)), h, w, r0, int(rng.integers(r0, h + 1)),
                      int(rng.integers(0, 12))))
    for cap, h, w, r0, r1, n in cases:
        ring, slots, times, start, t0, t1, end_slot = _interp_case(rng, cap, h, w, r0, r1, n)
        want = NB.interpolate_band(ring.copy(), slots, times, r0, r1, start, t0, t1, end_slot)
        got = ring.copy()
        interpolate_band(got, slots, times, r0, r1, start, t0, t1, end_slot)
        np.testing.assert_array_equal(got, want)


def test_interpolate_band_static_rows_stay_exact():
    """A band whose rows did not change between its renders (a static band) stays exactly
    its value in every frame between."""
    ring = np.zeros((4, 6, 5), np.float32)
    start = np.full((6, 5), 0.7312, np.float32)
    ring[3] = start
    interpolate_band(ring, np.array([0, 1, 2]), np.array([10, 500, 999]), 0, 6, start, 0,
                     1000, 3)
    assert (ring[:3] == np.float32(0.7312)).all()


@pytest.mark.parametrize("kw", [dict(), dict(dynamics="pitch", start_m=0.0),
                                dict(start_m=272.0, width=33, height=25)])
def test_render_row_set_vs_naive(kw):
    """Chosen rows (any order, interleaved between threads, the last rows before contact)
    equal the whole frame's rows (numpy reference) and their speed bounds the per-row maxima
    of the reference's motion field; other rows are left alone."""
    sc = Scene.from_params(**{**SMALL, **kw})
    cam = sc.camera
    k = cam.supersample
    sub = (np.arange(k) + 0.5) / k - 0.5
    xs = (np.arange(cam.width)[:, None] + sub[None, :]).ravel()
    rng = np.random.default_rng(1)
    for t in (0.0, 0.37):
        want = N.render(sc, t)
        o, rot, vc, wc = sc.state(t)
        for rows in (np.arange(cam.height), np.array([cam.height - 1]), np.array([], int),
                     rng.permutation(cam.height)[:7]):
            rows = rows.astype(np.int64)
            out = np.full((cam.height, cam.width), -1.0, np.float32)
            v2 = np.full(cam.height, -1.0)
            for i0 in range(2):
                render_row_set(*sc._frame_args(t, out, sc._scratch()), rows, i0, 2, v2)
            rest = np.setdiff1d(np.arange(cam.height), rows)
            assert (out[rest] == -1).all() and (v2[rest] == -1).all()
            np.testing.assert_allclose(out[rows], want[rows], rtol=2e-6, atol=2e-6)
            for j in rows:
                ys = np.full(xs.shape, j + sub[0])
                tb = N.trace(o, N.rays(xs, ys, cam.f, cam.cx, cam.cy, rot), sc.boxes)[0]
                ref = N.row_speed2_max((xs - cam.cx) / cam.f, (j + sub[0] - cam.cy) / cam.f,
                                       tb, cam.f, vc, wc)
                assert v2[j] == pytest.approx(ref, rel=1e-9)


def _dt_rule(max_motion_px=0.5, dt_min=5, dt_max=10_000):
    return StepRule(max_motion_px, dt_min, dt_max)


def _whole(sc, end_us, rule):
    return [(t, f) for t, f, _ in sc.frames(0, end_us, lambda v: int(step_us(rule, v)))]


def test_step_rule_vs_naive():
    """The step kernel against the plain rule: at rest, tiny and huge speeds, both clips."""
    rng = np.random.default_rng(3)
    speeds = [0.0, -1.0, 1e-12, 1e-3, 49.99, 50.0, 1e5, 1e6, 1e300, *rng.uniform(0, 2e5, 200)]
    for mm, lo, hi in [(0.5, 5, 10_000), (0.125, 1, 100), (2.0, 20, 20)]:
        rule = StepRule(mm, lo, hi)
        for v in speeds:
            assert int(step_us(rule, v)) == NB.step_us(mm, lo, hi, v), (mm, v)


def test_rows_of_vs_naive():
    """The rows of marked bands: none, all, a last band shorter than the others, one row."""
    rng = np.random.default_rng(6)
    for edges in ([0, 16, 30], [0, 1, 2, 3], [0, 7, 14, 21, 28, 30], [0, 30]):
        edges = np.array(edges, np.int64)
        nb = len(edges) - 1
        for bands in (np.zeros(nb, bool), np.ones(nb, bool), *(rng.random((20, nb)) < 0.5)):
            rows = np.full(40, -1, np.int64)
            n = rows_of(bands, edges, rows)
            want = [r for b in np.flatnonzero(bands) for r in range(edges[b], edges[b + 1])]
            assert rows[:n].tolist() == want and (rows[n:] == -1).all()


def test_predict_vs_naive():
    """The prediction of the next frames' due bands against the rule applied frame by frame:
    random states, a ring about to fill, the end of the drive within the horizon."""
    rng = np.random.default_rng(4)
    for _ in range(300):
        nb = int(rng.integers(1, 12))
        cap = int(rng.integers(1, 10))
        t = int(rng.integers(0, 5000))
        dt = int(rng.integers(1, 500))
        end = t + int(rng.integers(1, 12 * dt))
        last = np.where(rng.random(nb) < 0.1, -1, t - rng.integers(1, 3000, nb)).astype(np.int64)
        band_dt = rng.integers(1, 3000, nb).astype(np.int64)
        nwait = int(rng.integers(0, cap))
        waiting = np.sort(t - rng.integers(1, 2000, nwait)).astype(np.int64)
        masks = np.zeros((int(rng.integers(1, 6)), nb), bool)
        n = predict(t, dt, end, cap, waiting, last, band_dt, masks)
        want = NB.predict(t, dt, end, cap, waiting, last, band_dt, masks.shape[0])
        assert n == len(want)
        np.testing.assert_array_equal(masks[:n], want)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("band_rows, capacity, dynamics",
                         [(16, 64, "constant"), (7, 4, "constant"), (1, 1, "constant"),
                          (4, 8, "pitch")])
def test_schedule_vs_naive(threads, band_rows, capacity, dynamics):
    """The schedule (compiled rule; with two threads also the renders predicted ahead) gives
    the plain schedule's frames, steps and renders, bit for bit: bands of several sizes, a
    ring that fills (capacity 4) or holds one frame, a pitching camera whose speeds change."""
    kw = dict(SMALL, dynamics=dynamics, start_m=0.0 if dynamics == "pitch" else 200.0)
    sc = Scene.from_params(threads=threads, **kw)
    rule = _dt_rule()
    bands = BandFrames(sc, band_rows, capacity)
    log = _log_renders(bands)
    got = list(bands.frames(0, 30_000, rule))
    ref = Scene.from_params(**kw)

    def render(t, out, rows, row_v2):
        render_row_set(*ref._frame_args(t * 1e-6, out, ref._scratch()), rows, 0, 1, row_v2)

    want, renders = NB.band_frames(render, 30, 40, bands.edges, capacity, 0, 30_000,
                                   lambda v: NB.step_us(0.5, 5, 10_000, v))
    assert [(g[0], g[2]) for g in got] == [(w[0], w[2]) for w in want] and len(got) > 5
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g[1], w[1])
    assert [(t, sorted(rows)) for t, rows in log] == renders


@pytest.mark.parametrize("band_rows", [16, 7, 1])
def test_bands_render_where_due_and_interpolate_between(band_rows):
    """Every band's rows equal the whole frame at the times it renders, lie on the straight
    line between its renders in the frames between (within float32), no band moves more than
    max_motion_px / 1.5 between renders more than one frame apart (exact flow at the earlier
    render), the image's height (30) is not a multiple of every band size, and the global
    times are the fastest band's."""
    sc = Scene.from_params(**SMALL)
    bands = BandFrames(sc, band_rows, capacity=64)
    rendered = _log_renders(bands)
    got = list(bands.frames(0, 30_000, _dt_rule()))
    t = np.array([g[0] for g in got])
    assert t[0] == 0 and np.all(np.diff(t) > 0) and t[-1] < 30_000
    assert all(g[0] + g[2] == h[0] for g, h in zip(got[:-1], got[1:], strict=True))
    frames = np.stack([g[1] for g in got])
    whole = np.stack([sc.render(ti * 1e-6)[0] for ti in t])
    # the bound's samples: every sample column of the first sample row of each pixel row
    ys, xs = np.mgrid[0:30, 0:80].astype(float)
    xs = (xs + 0.5) / 2 - 0.5
    ys = ys - 0.25
    share = 0
    index = {int(ti): i for i, ti in enumerate(t)}
    for b in range(bands.nbands):
        r0, r1 = bands.edges[b], bands.edges[b + 1]
        renders = [index[tr] for tr, rows in rendered if r0 in rows]
        assert renders[0] == 0 and renders[-1] == len(t) - 1
        assert all(set(range(r0, r1)) <= set(rows) for _, rows in rendered if r0 in rows)
        share += len(renders) * (r1 - r0)
        for i in renders:
            np.testing.assert_array_equal(frames[i, r0:r1], whole[i, r0:r1])
        for i0, i1 in zip(renders[:-1], renders[1:], strict=True):
            vx, vy = sc_flow(sc, xs[r0:r1], ys[r0:r1], t[i0])
            bound = 0.5 if i1 == i0 + 1 else 0.5 / 1.5     # consecutive frames: the global step
            assert np.hypot(vx, vy).max() * (t[i1] - t[i0]) * 1e-6 <= bound + 1e-9
            a, c = frames[i0, r0:r1], frames[i1, r0:r1]
            for i in range(i0 + 1, i1):
                w = (t[i] - t[i0]) / (t[i1] - t[i0])
                np.testing.assert_allclose(frames[i, r0:r1], a + w * (c - a), atol=1e-6)
    assert bands.rows_rendered == share
    if band_rows < 30:       # the slow top bands render less often than the bottom one
        assert share < 0.9 * len(t) * 30


def _log_renders(bands):
    """(t, rows) of every render of ``bands``, recorded by wrapping its row renderer."""
    log = []
    render = bands._render_rows

    def logged(t_us, out, rows, row_v2):
        log.append((int(t_us), set(int(r) for r in rows)))
        render(t_us, out, rows, row_v2)

    bands._render_rows = logged
    return log


def sc_flow(sc, xs, ys, t_us):
    from evchain.sim.truth import SceneTruth

    return SceneTruth(sc).flow(xs, ys, float(t_us))


def test_one_band_is_the_whole_frame():
    """A band as tall as the image renders every frame whole: the same times and bits."""
    sc = Scene.from_params(**SMALL)
    got = list(BandFrames(sc, 30, capacity=8).frames(0, 20_000, _dt_rule()))
    want = _whole(sc, 20_000, _dt_rule())
    assert [g[0] for g in got] == [w[0] for w in want]
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g[1], w[1])


def test_static_scene_and_full_ring():
    """A camera at rest (motion bound 0) steps at dt_max; a ring of one frame renders every
    band every frame (the same frames as whole)."""
    sc = Scene.from_params(**{**SMALL, "speed_mps": 0.0, "duration_s": 0.1})
    got = list(BandFrames(sc, 8, capacity=4).frames(0, 30_000, _dt_rule()))
    assert [g[0] for g in got] == [0, 10_000, 20_000]
    sc = Scene.from_params(**SMALL)
    got = list(BandFrames(sc, 8, capacity=1).frames(0, 10_000, _dt_rule()))
    want = _whole(sc, 10_000, _dt_rule())
    assert [g[0] for g in got] == [w[0] for w in want]
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g[1], w[1])


def test_threads_render_the_same_frames():
    """Two threads taking pieces of a frame's rows (several pieces per frame at 64 rows) give
    the frames of one thread, bit for bit."""
    kw = dict(SMALL, width=48, height=64)
    got = list(BandFrames(Scene.from_params(threads=2, **kw), 4, 8).frames(0, 40_000, _dt_rule()))
    want = list(BandFrames(Scene.from_params(**kw), 4, 8).frames(0, 40_000, _dt_rule()))
    assert [g[0] for g in got] == [w[0] for w in want] and len(got) > 3
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g[1], w[1])


def test_source_band_rows_and_fixed_step():
    """The source with band_rows: frames at increasing times, its rendered share in the
    metrics; with dt_us every frame renders whole (no share reported)."""
    params = dict(SMALL, duration_s=0.02, band_rows=8, threads=2)
    f = SceneSource()
    ctx = make_context(None)
    f.setup(SceneSource.Params(**params), ctx)
    packets = list(f.packets())
    t = np.concatenate([p.t for p in packets])
    assert np.all(np.diff(t) > 0) and 0 < ctx.metrics["scene"]["rendered_share"] < 1
    f = SceneSource()
    ctx = make_context(None)
    f.setup(SceneSource.Params(**dict(params, dt_us=2000)), ctx)
    packets = list(f.packets())
    assert "rendered_share" not in ctx.metrics["scene"]


def test_banded_events_agree_with_whole_frames():
    """scene -> emulator of pipelines/reference.yaml, 320x240, the last 40 ms before the
    obstacle: the banded run's events against whole frames' within the stated tolerances
    (total count 0.5 %, median |time difference| of matched events 1 µs), with fewer rows
    rendered."""
    from evchain.benchmarks.scene_bands import agreement

    res = agreement(["scene.start_m=275", "scene.duration_s=0.04", "scene.threads=1"],
                    band_rows=16)
    assert res["n_a"] > 10_000
    assert res["banded"]["rendered_share"] < 0.75
    assert abs(res["count_rel_diff"]) <= 0.005
    assert res["pixels_differing"] < 0.01
    assert res["median_abs_dt_us"] <= 1.0


def test_predictions_pause_after_misses_and_resume_on_a_hit():
    """A frame asked for without a render ahead (or with renders of earlier times left) is a
    miss: no predictions for AHEAD frames, twice as long after each further miss (at most
    MAX_PAUSE); asking again for the same frame is not another miss; a render ahead that
    holds ends the count."""
    from concurrent.futures import Future, ThreadPoolExecutor

    class Stub:
        def _nthreads(self):
            return 2

        def _pool_of(self, n):
            return ThreadPoolExecutor(1)

    ahead = _Ahead(Stub(), 4, 3, np.array([0, 2, 4]))
    out, v2, rows = np.zeros((4, 3), np.float32), np.zeros(4), np.arange(4)
    t = 0
    pauses = []
    for _ in range(7):
        assert ahead.predicting()
        np.testing.assert_array_equal(ahead.take(t, out, rows, v2), rows)   # a miss
        ahead.take(t, out, rows[:2], v2)                                    # same frame
        n = 0
        while not ahead.predicting():
            t += 10
            ahead.take(t, out, rows, v2)
            n += 1
        pauses.append(n)
        t += 10
    assert pauses == [min(MAX_PAUSE, AHEAD << k) for k in range(7)]
    # a hit: the rows of its bands come from the render ahead, and the count starts over
    done = Future()
    done.set_result(None)
    frame = np.full((4, 3), 7, np.float32)
    ahead.jobs[t] = (np.array([True, False]), done, frame, np.full(4, 3.0))
    np.testing.assert_array_equal(ahead.take(t, out, rows, v2), [2, 3])
    assert (out[:2] == 7).all() and ahead.predicting() and ahead.misses == 0
    ahead.take(t + 10, out, rows, v2)
    assert not ahead.predicting() and ahead.pause == AHEAD
