"""The scene's row bands (``band_rows``): kernels against tests/naive, the schedule's rules and
the events against frames rendered whole."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.filters.scene import SceneSource
from evchain.kernels.scene_bands import interpolate_tiles
from evchain.kernels.scene_render import render_spans
from evchain.sim.bands import BandFrames
from evchain.sim.drive import Scene
from evchain.testing.contract import make_context
from tests.naive import scene_bands as NB
from tests.naive import scene_kernels as N

SMALL = dict(width=40, height=30, supersample=2, start_m=200.0)


def _interp_case(rng, cap, h, w, nslots, band_rows, band_cols):
    ring = rng.uniform(0, 3, (cap, h, w)).astype(np.float32)
    start = rng.uniform(0, 3, (h, w)).astype(np.float32)
    end_slot = int(rng.integers(cap))
    others = np.setdiff1d(np.arange(cap), [end_slot])
    slots = rng.choice(others, size=min(nslots, len(others)), replace=False).astype(np.int64)
    t1 = int(rng.integers(1000, 6000))
    times = np.sort(rng.integers(0, t1, len(slots))).astype(np.int64)
    redges = _edges(h, band_rows)
    cedges = _edges(w, band_cols)
    shape = (len(redges) - 1, len(cedges) - 1)
    done = rng.uniform(size=shape) < 0.6
    # earlier renders: none (-1), before every frame, or between the frames
    last_t = rng.integers(-1, t1, shape).astype(np.int64)
    last_t[rng.uniform(size=shape) < 0.2] = -1
    return ring, slots, times, done, last_t, redges, cedges, start, t1, end_slot


def _edges(n, size):
    return np.unique(np.arange(0, n + size, size).clip(max=n)).astype(np.int64)


def test_interpolate_tiles_vs_naive_random_and_edges():
    rng = np.random.default_rng(5)
    cases = [(8, 30, 40, 5, 16, 40),      # row bands, the last shorter than the others
             (8, 30, 40, 7, 16, 16),      # tiles, the last column and row shorter
             (3, 5, 7, 2, 1, 7),          # bands of one row
             (4, 6, 9, 3, 6, 1),          # tiles of one column
             (5, 6, 9, 0, 2, 3)]          # no frame between
    for _ in range(20):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 50))
        cases.append((int(rng.integers(2, 12)), h, w, int(rng.integers(0, 12)),
                      int(rng.integers(1, h + 1)), int(rng.integers(1, w + 1))))
    for cap, h, w, n, br, bc in cases:
        args = _interp_case(rng, cap, h, w, n, br, bc)
        ring, start = args[0], args[7]
        want_ring, want_start = NB.interpolate_tiles(ring.copy(), *args[1:7], start.copy(),
                                                     *args[8:])
        got_ring, got_start = ring.copy(), start.copy()
        interpolate_tiles(got_ring, *args[1:7], got_start, *args[8:])
        np.testing.assert_array_equal(got_ring, want_ring)
        np.testing.assert_array_equal(got_start, want_start)
        assert args[3].any() or (got_ring == ring).all()


def test_interpolate_tiles_static_tile_stays_exact():
    """A tile whose pixels did not change between its renders (a static tile) stays exactly
    its value in every frame between; tiles not done are left alone."""
    ring = np.zeros((4, 6, 5), np.float32)
    start = np.full((6, 5), 0.7312, np.float32)
    ring[3] = start
    done = np.array([[True, False]])
    interpolate_tiles(ring, np.array([0, 1, 2]), np.array([10, 500, 999]), done,
                      np.array([[0, 0]]), np.array([0, 6]), np.array([0, 3, 5]), start, 1000, 3)
    assert (ring[:3, :, :3] == np.float32(0.7312)).all() and (ring[:3, :, 3:] == 0).all()


@pytest.mark.parametrize("kw", [dict(), dict(dynamics="pitch", start_m=0.0),
                                dict(start_m=272.0, width=33, height=25)])
def test_render_spans_vs_naive(kw):
    """Chosen rows, whole or in tiles of 8 columns (any order, interleaved between threads, the
    last rows before contact), equal the whole frame's pixels (numpy reference) and their
    tiles' speed bounds the maxima of the reference's motion field over the tile's samples;
    other pixels and bounds are left alone."""
    sc = Scene.from_params(**{**SMALL, **kw})
    cam = sc.camera
    k = cam.supersample
    sub = (np.arange(k) + 0.5) / k - 0.5
    xs = (np.arange(cam.width)[:, None] + sub[None, :]).ravel()
    rng = np.random.default_rng(1)
    for t in (0.0, 0.37):
        want = N.render(sc, t)
        o, rot, vc, wc = sc.state(t)
        for tcols in (cam.width, 8):
            edges = np.unique(np.arange(0, cam.width + tcols, tcols).clip(max=cam.width))
            nt = len(edges) - 1
            tiles = [(j, c) for j in range(cam.height) for c in range(nt)]
            for pick in (len(tiles), 1, 0, 11):
                chosen = [tiles[i] for i in rng.permutation(len(tiles))[:pick]]
                rows = np.array([j for j, _ in chosen], np.int64)
                x0s = np.array([edges[c] for _, c in chosen], np.int64)
                x1s = np.array([edges[c + 1] for _, c in chosen], np.int64)
                out = np.full((cam.height, cam.width), -1.0, np.float32)
                v2 = np.full((cam.height, nt), -1.0)
                for i0 in range(2):
                    render_spans(*sc._frame_args(t, out, sc._scratch()), rows, x0s, x1s, tcols,
                                 i0, 2, v2)
                mask = np.zeros(out.shape, bool)
                vmask = np.zeros(v2.shape, bool)
                for j, c in chosen:
                    mask[j, edges[c]:edges[c + 1]] = True
                    vmask[j, c] = True
                assert (out[~mask] == -1).all() and (v2[~vmask] == -1).all()
                np.testing.assert_allclose(out[mask], want[mask], rtol=2e-6, atol=2e-6)
                for j, c in chosen:
                    ys = np.full(xs.shape, j + sub[0])
                    tb = N.trace(o, N.rays(xs, ys, cam.f, cam.cx, cam.cy, rot), sc.boxes)[0]
                    cols = slice(edges[c] * k, edges[c + 1] * k)
                    ref = N.row_speed2_max((xs[cols] - cam.cx) / cam.f,
                                           (j + sub[0] - cam.cy) / cam.f, tb[cols], cam.f, vc,
                                           wc)
                    assert v2[j, c] == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize("kw", [dict(), dict(dynamics="pitch", start_m=0.0),
                                dict(scenario="curves", dynamics="curves", start_m=80.0),
                                dict(scenario="open-field", start_m=40.0),
                                dict(start_m=272.0, width=33, height=25)])
def test_rows_in_column_pieces_equal_whole_rows(kw):
    """Every row cut into random column pieces (pieces of all rows in random order through
    one scratch, and each piece alone) gives the whole frame's bits, at several times; the
    pieces' speed bounds, taken as one tile, give the row's."""
    sc = Scene.from_params(**{**SMALL, **kw})
    h, w = sc.camera.height, sc.camera.width
    rng = np.random.default_rng(3)
    for t in (0.0, 0.37, 1.21):
        whole, vmax = sc.render(t)
        rows, x0s, x1s = [], [], []
        for j in range(h):
            cuts = np.unique(np.r_[0, rng.integers(1, w, int(rng.integers(0, 6))), w])
            rows += [j] * (len(cuts) - 1)
            x0s += list(cuts[:-1])
            x1s += list(cuts[1:])
        order = rng.permutation(len(rows))
        rows, x0s, x1s = (np.array(a, np.int64)[order] for a in (rows, x0s, x1s))
        out = np.full((h, w), -1.0, np.float32)
        v2 = np.zeros((h, 1))
        render_spans(*sc._frame_args(t, out, sc._scratch()), rows, x0s, x1s, w, 0, 1, v2)
        np.testing.assert_array_equal(out, whole)
        alone = np.full((h, w), -1.0, np.float32)
        v2[:] = 0.0
        v2_alone = np.zeros((h, 1))
        for i in range(len(rows)):
            render_spans(*sc._frame_args(t, alone, sc._scratch()), rows[i:i + 1],
                         x0s[i:i + 1], x1s[i:i + 1], w, 0, 1, v2_alone)
            v2[rows[i], 0] = max(v2[rows[i], 0], v2_alone[rows[i], 0])
        np.testing.assert_array_equal(alone, whole)
        assert np.sqrt(v2.max()) == vmax


def _dt_rule(max_motion_px=0.5, dt_min=5, dt_max=10_000):
    """The source's step rule (for a speed or an array of speeds)."""
    return _DtRule(max_motion_px, dt_min, dt_max).next_dt_us


class _DtRule:
    def __init__(self, max_motion_px, dt_min, dt_max):
        self.params = SceneSource.Params(max_motion_px=max_motion_px, dt_min_us=dt_min,
                                         dt_max_us=dt_max)

    next_dt_us = SceneSource.next_dt_us


def test_step_rule_on_arrays_is_the_rule_on_each_speed():
    rule = _dt_rule()
    v = np.array([0.0, -1.0, 1e-300, 1e-3, 3.7, 49.999, 50.0, 1234.5, 1e5, 1e9])
    assert rule(v).tolist() == [rule(float(x)) for x in v[:2]] + [10_000] + \
        [rule(float(x)) for x in v[3:]]
    assert rule(v).dtype == np.int64


def _whole(sc, end_us, next_dt):
    return [(t, f) for t, f, _ in sc.frames(0, end_us, next_dt)]


@pytest.mark.parametrize("band_rows, band_cols", [(16, 0), (7, 0), (1, 0), (16, 16), (7, 6),
                                                  (30, 8)])
def test_bands_render_where_due_and_interpolate_between(band_rows, band_cols):
    """Every tile (band, or block of a band's columns) equals the whole frame at the times it
    renders, lies on the straight line between its renders in the frames between (within
    float32), no tile moves more than max_motion_px / 1.5 between renders more than one frame
    apart (exact flow at the earlier render), the image (40x30) is not a multiple of every
    tile size, and the global times are the fastest tile's."""
    sc = Scene.from_params(**SMALL)
    next_dt = _dt_rule()
    bands = BandFrames(sc, band_rows, capacity=64, band_cols=band_cols)
    rendered = _log_renders(bands)
    got = list(bands.frames(0, 30_000, next_dt))
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
    (nb, nc), redges, cedges = bands.shape, bands.edges, bands.col_edges
    assert nc == (1 if band_cols == 0 else -(-40 // band_cols))
    for b in range(nb):
        r0, r1 = redges[b], redges[b + 1]
        for c in range(nc):
            x0, x1 = cedges[c], cedges[c + 1]
            tile = (slice(r0, r1), slice(x0, x1))
            renders = [index[tr] for tr, mask in rendered if mask[r0, x0]]
            assert renders[0] == 0 and renders[-1] == len(t) - 1
            assert all(mask[tile].all() for _, mask in rendered if mask[r0, x0])
            share += len(renders) * (r1 - r0) * (x1 - x0)
            for i in renders:
                np.testing.assert_array_equal(frames[i][tile], whole[i][tile])
            samples = (slice(r0, r1), slice(2 * x0, 2 * x1))
            for i0, i1 in zip(renders[:-1], renders[1:], strict=True):
                vx, vy = sc_flow(sc, xs[samples], ys[samples], t[i0])
                bound = 0.5 if i1 == i0 + 1 else 0.5 / 1.5    # consecutive: the global step
                assert np.hypot(vx, vy).max() * (t[i1] - t[i0]) * 1e-6 <= bound + 1e-9
                a, e = frames[i0][tile], frames[i1][tile]
                for i in range(i0 + 1, i1):
                    w = (t[i] - t[i0]) / (t[i1] - t[i0])
                    np.testing.assert_allclose(frames[i][tile], a + w * (e - a), atol=1e-6)
    assert bands.pixels_rendered == share
    if nb > 1:       # the slow top tiles render less often than the bottom ones
        assert share < 0.9 * len(t) * 30 * 40


def _log_renders(bands):
    """(t, mask of the pixels rendered) of every render of ``bands``, recorded by wrapping its
    renderer."""
    log = []
    render = bands._render_spans

    def logged(t_us, out, rows, x0s, x1s, v2):
        mask = np.zeros(out.shape, bool)
        for j, x0, x1 in zip(rows, x0s, x1s, strict=True):
            assert not mask[j, x0:x1].any()         # every pixel once
            mask[j, x0:x1] = True
        log.append((int(t_us), mask))
        render(t_us, out, rows, x0s, x1s, v2)

    bands._render_spans = logged
    return log


def sc_flow(sc, xs, ys, t_us):
    from evchain.sim.truth import SceneTruth

    return SceneTruth(sc).flow(xs, ys, float(t_us))


@pytest.mark.parametrize("band_cols", [0, 40, 64])
def test_one_band_is_the_whole_frame(band_cols):
    """A band as tall as the image (one tile as large) renders every frame whole: the same
    times and bits."""
    sc = Scene.from_params(**SMALL)
    next_dt = _dt_rule()
    got = list(BandFrames(sc, 30, capacity=8, band_cols=band_cols).frames(0, 20_000, next_dt))
    want = _whole(sc, 20_000, next_dt)
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
    want = _whole(sc, 10_000, _dt_rule())
    for band_cols in (0, 8):
        got = list(BandFrames(sc, 8, capacity=1, band_cols=band_cols).frames(0, 10_000,
                                                                              _dt_rule()))
        assert [g[0] for g in got] == [w[0] for w in want]
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g[1], w[1])


@pytest.mark.parametrize("band_cols", [0, 10])
def test_threads_render_the_same_frames(band_cols):
    """Two threads taking pieces of a frame's rows (several pieces per frame at 64 rows) give
    the frames of one thread, bit for bit."""
    kw = dict(SMALL, width=48, height=64)
    got = list(BandFrames(Scene.from_params(threads=2, **kw), 4, 8, band_cols).frames(
        0, 40_000, _dt_rule()))
    want = list(BandFrames(Scene.from_params(**kw), 4, 8, band_cols).frames(0, 40_000,
                                                                           _dt_rule()))
    assert [g[0] for g in got] == [w[0] for w in want] and len(got) > 3
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g[1], w[1])


@pytest.mark.parametrize("band_cols", [0, 8])
def test_source_band_rows_and_fixed_step(band_cols):
    """The source with band_rows (and tiles): frames at increasing times, its rendered share
    in the metrics; with dt_us every frame renders whole (no share reported); band_cols
    without band_rows is refused."""
    params = dict(SMALL, duration_s=0.02, band_rows=8, band_cols=band_cols, threads=2,
                  contrast=0.7)
    f = SceneSource()
    ctx = make_context(None)
    f.setup(SceneSource.Params(**params), ctx)
    packets = list(f.packets())
    t = np.concatenate([p.t for p in packets])
    assert np.all(np.diff(t) > 0) and 0 < ctx.metrics["scene"]["rendered_share"] < 1
    # contrast applied once to every rendered pixel: the first frame is the whole frame's
    np.testing.assert_array_equal(packets[0].frames[0],
                                  Scene.from_params(**{k: v for k, v in params.items() if k
                                                       in ("width", "height", "supersample",
                                                           "start_m", "contrast")}
                                                    ).render(0.0)[0])
    with pytest.raises(ValueError, match="band_cols 4 needs band_rows"):
        SceneSource.Params(**dict(params, band_rows=0, band_cols=4))
    f = SceneSource()
    ctx = make_context(None)
    f.setup(SceneSource.Params(**dict(params, dt_us=2000)), ctx)
    packets = list(f.packets())
    assert "rendered_share" not in ctx.metrics["scene"]


@pytest.mark.parametrize("band_cols, share", [(0, 0.75), (16, 0.6)])
def test_banded_events_agree_with_whole_frames(band_cols, share):
    """scene -> emulator of pipelines/reference.yaml, 320x240, the last 40 ms before the
    obstacle: the banded (tiled) run's events against whole frames' within the stated
    tolerances (total count 0.5 %, median |time difference| of matched events 1 µs), with
    fewer pixels rendered."""
    from evchain.benchmarks.scene_bands import agreement

    res = agreement(["scene.start_m=275", "scene.duration_s=0.04", "scene.threads=1"],
                    band_rows=16, band_cols=band_cols)
    assert res["n_a"] > 10_000
    assert res["banded"]["rendered_share"] < share
    assert abs(res["count_rel_diff"]) <= 0.005
    assert res["pixels_differing"] < 0.01
    assert res["median_abs_dt_us"] <= 1.0
