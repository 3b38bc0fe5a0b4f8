"""plane_flow kernels against the slow reference (tests/naive/plane_flow.py), known edges and
hard inputs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evchain.core.packets import Geometry
from evchain.kernels.plane_flow import (
    VARIANTS,
    WHY_NO_FLOW,
    PlaneParams,
    fit_explicit,
    new_state,
    plane_flow_adaptive_kernel,
    plane_flow_kernel,
    smallest_eigvec3,
)
from evchain.kernels.records import record
from evchain.testing.synthetic import moving_edge_events, random_events
from tests.naive.plane_flow import plane_flow_naive

DEFAULTS = dict(variant="single", r=2, window_us=80_000, refractory_us=0, margin=None,
                min_points=3, th1=1e-5, th2=0.01, max_speed=1e4, max_iter=10,
                min_spread=0.0, centre_check=False, max_window_us=0, slow_px=2.0,
                refit_failed=True, refractory_updates=True, min_window_us=0, fast_px=4.0)
FITTING = ("single", "iterative", "robust", "savitzky_golay")


def run_kernel(x, y, t, p, width, height, counts=None, **kw):
    """The kernel's flow events (index, vx, vy); ``counts`` (int64[8]) is added to."""
    q = {**DEFAULTS, **kw}
    ts = new_state(width, height)
    n = len(t)
    idx, vx, vy = np.empty(n, np.int64), np.empty(n), np.empty(n)
    margin = q["r"] if q["margin"] is None else q["margin"]
    prm = record(PlaneParams, **{**{k: v for k, v in q.items() if k in PlaneParams._fields},
                                 "variant": VARIANTS[q["variant"]], "margin": margin})
    counts = np.zeros(len(WHY_NO_FLOW) + 1, np.int64) if counts is None else counts
    k = plane_flow_kernel(np.asarray(x, np.uint16), np.asarray(y, np.uint16),
                          np.asarray(t, np.int64), np.asarray(p, np.int8), ts, prm, idx, vx, vy,
                          counts)
    return idx[:k], vx[:k], vy[:k]


def run_naive(x, y, t, p, width, height, counts=None, **kw):
    q = {**DEFAULTS, **kw}
    return plane_flow_naive(x, y, t, p, width, height, q["variant"], q["r"], q["window_us"],
                            q["refractory_us"], q["margin"], q["min_points"], q["th1"], q["th2"],
                            q["max_speed"], q["max_iter"], q["min_spread"],
                            q["centre_check"], q["max_window_us"], q["slow_px"],
                            q["refit_failed"], q["refractory_updates"], q["min_window_us"],
                            q["fast_px"], counts)


def assert_same(ev, width, height, **kw):
    """Kernel and reference give the same flow events and the same reasons for the rest."""
    counts, why = np.zeros(len(WHY_NO_FLOW) + 1, np.int64), {}
    a = run_kernel(ev.x, ev.y, ev.t, ev.p, width, height, counts=counts, **kw)
    b = run_naive(ev.x, ev.y, ev.t, ev.p, width, height, counts=why, **kw)
    np.testing.assert_array_equal(a[0], b[0])
    assert counts.sum() == len(ev.t) and counts[-1] == len(a[0])
    assert dict(zip((*WHY_NO_FLOW, "flow"), counts.tolist(), strict=True)) == {
        k: why.get(k, 0) for k in (*WHY_NO_FLOW, "flow")}
    np.testing.assert_allclose(a[1], b[1], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a[2], b[2], rtol=1e-6, atol=1e-6)
    assert np.isfinite(a[1]).all() and np.isfinite(a[2]).all()
    return a


# ------------------------------------------------------------------ kernel vs reference


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("centre_check", [False, True])
def test_random_stream_matches_reference(variant, centre_check):
    g = Geometry(24, 20)
    ev = random_events(1500, g, 0, 150_000, seed=11)
    got = assert_same(ev, g.width, g.height, variant=variant, refractory_us=3000,
                      centre_check=centre_check, th2=0.02)
    assert len(got[0]) > 20  # the comparison is not vacuous


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), variant=st.sampled_from(list(VARIANTS)),
       r=st.integers(1, 3), window_us=st.integers(5_000, 200_000),
       refractory_us=st.integers(0, 20_000), margin=st.integers(0, 4),
       min_points=st.integers(3, 8), th2=st.sampled_from([1e-3, 1e-2, 5e-2]),
       min_spread=st.sampled_from([0.0, 0.3, 0.6]), centre_check=st.booleans())
def test_random_parameters_match_reference(seed, variant, r, window_us, refractory_us, margin,
                                           min_points, th2, min_spread, centre_check):
    g = Geometry(16, 14)
    ev = random_events(500, g, 0, 100_000, seed=seed)
    assert_same(ev, g.width, g.height, variant=variant, r=r, window_us=window_us,
                refractory_us=refractory_us, margin=margin, min_points=min_points, th2=th2,
                max_speed=200.0, min_spread=min_spread, centre_check=centre_check)


def test_spread_bound_tie_matches_reference():
    """An event whose neighbours' least spread is exactly min_spread (5 points, covariance
    eigenvalue 0.36 = 0.6^2): kernel and reference must decide the tie alike (an eigenvalue
    formula rounded it to either side, so they disagreed on event 145)."""
    g = Geometry(16, 14)
    ev = random_events(500, g, 0, 100_000, seed=24)
    got = assert_same(ev, g.width, g.height, variant="single", r=2, window_us=10519,
                      refractory_us=0, margin=0, min_points=3, th2=1e-3, max_speed=200.0,
                      min_spread=0.6, centre_check=False)
    assert 145 in got[0]  # the tie passes the bound (>=)


def test_noisy_edge_matches_reference():
    """A moving edge with jittered timestamps and noise: iterations actually drop points."""
    g = Geometry(32, 24)
    edge = moving_edge_events(60.0, 25.0, g, duration_us=600_000)
    rng = np.random.default_rng(4)
    t = np.sort(edge.t + rng.integers(0, 3000, len(edge.t)))
    noise = random_events(150, g, 0, 600_000, seed=5)
    x = np.concatenate([edge.x, noise.x])
    y = np.concatenate([edge.y, noise.y])
    tt = np.concatenate([t, noise.t])
    p = np.concatenate([edge.p, np.ones(len(noise.p), np.int8)])
    o = np.argsort(tt, kind="stable")
    ev = edge.replace(x=x[o], y=y[o], t=tt[o], p=p[o], t_end=int(tt.max()) + 1)
    for variant in VARIANTS:
        for centre_check in (False, True):
            assert_same(ev, g.width, g.height, variant=variant, window_us=200_000, th2=2e-3,
                        centre_check=centre_check)


def test_eigvec_matches_numpy():
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = rng.normal(size=(3, 3)) * rng.choice([1e-3, 1.0, 30.0], 3)
        m = a @ a.T
        ok, v0, v1, v2 = smallest_eigvec3(m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2], m[2, 2])
        w, vecs = np.linalg.eigh(m)
        assert ok
        ref = vecs[:, 0] * np.sign(vecs[2, 0])
        assert np.allclose([v0, v1, v2], ref, atol=1e-6 * (1 + w[2] / max(w[1] - w[0], 1e-300)))
    ok, *_ = smallest_eigvec3(2.0, 0.0, 0.0, 1.0, 0.0, 1.0)  # smallest eigenvalue repeated
    assert not ok
    ok, *_ = smallest_eigvec3(1.0, 0.0, 0.0, 1.0, 0.0, 1.0)  # all equal
    assert not ok


# ------------------------------------------------------------------ known edges


SPEEDS = [1.0, 10.0, 100.0, 1000.0, 5000.0]
ANGLES = list(range(0, 360, 45))


@pytest.mark.parametrize("variant", FITTING)
def test_moving_edges_give_their_velocity(variant):
    """Straight edges in 8 directions at 1..5000 px/s; normal flow = velocity.

    Tolerance: every flow event within 3 % of the velocity (timestamps are whole µs), at least
    70 % of the events get flow (the first rows of pixels the edge crosses have no history).
    """
    g = Geometry(40, 32)
    for speed in SPEEDS:
        for ang in ANGLES:
            vx, vy = speed * np.cos(np.radians(ang)), speed * np.sin(np.radians(ang))
            ev = moving_edge_events(vx, vy, g, duration_us=int(60 / speed * 1e6))
            idx, ex, ey = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height,
                                     variant=variant, window_us=int(4 / speed * 1e6),
                                     th2=0.2 / speed, max_speed=1e5)
            assert len(idx) >= 0.7 * len(ev), (speed, ang, len(idx), len(ev))
            err = np.hypot(ex - vx, ey - vy) / speed
            assert err.max() < 0.03, (variant, speed, ang, err.max())


def test_original_variant_is_biased_and_skips_axis_edges():
    """The paper's per-component velocity: (1/a, 1/b) doubles a diagonal speed; an edge along
    an axis (a or b ~ 0) blows up to a huge speed that the ceiling rejects, and an exactly zero
    component is skipped, never divided by."""
    g = Geometry(40, 32)
    ev = moving_edge_events(100.0 / np.sqrt(2), 100.0 / np.sqrt(2), g, duration_us=600_000)
    idx, ex, ey = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, variant="original",
                             window_us=40_000)
    assert len(idx) > 0.7 * len(ev)
    np.testing.assert_allclose(np.hypot(ex, ey), 200.0, rtol=0.01)
    for vx, vy in [(100.0, 0.0), (0.0, -100.0)]:
        ev = moving_edge_events(vx, vy, g, duration_us=400_000)
        idx, ex, ey = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, variant="original",
                                 window_us=40_000)
        assert len(idx) == 0
        idx, ex, ey = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, variant="original",
                                 window_us=40_000, max_speed=1e300)
        assert np.isfinite(ex).all() and np.isfinite(ey).all()
        assert (np.hypot(ex, ey) > 1e6).all()


@pytest.mark.parametrize("variant", FITTING)
def test_speed_ceiling(variant):
    g = Geometry(40, 32)
    ev = moving_edge_events(300.0, 0.0, g, duration_us=150_000)
    kw = dict(variant=variant, window_us=20_000)
    assert len(run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, max_speed=310.0, **kw)[0])
    assert not len(run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, max_speed=290.0, **kw)[0])


# ------------------------------------------------------------------ hard cases


def step_square_events(steps=6, step_us=50_000, size=10, origin=(10, 10)):
    """DVSFLOW16-like: a square moving (+1, +1) px per step; all events of a step share one
    timestamp; leading edges ON, trailing edges OFF."""
    xs, ys, ts, ps = [], [], [], []
    for k in range(1, steps + 1):
        x0, y0 = origin[0] + k, origin[1] + k
        for j in range(size):
            for (x, y, p) in [(x0 + size - 1, y0 + j, 1), (x0 + j, y0 + size - 1, 1),
                              (x0 - 1, y0 + j, -1), (x0 + j, y0 - 1, -1)]:
                xs.append(x)
                ys.append(y)
                ts.append(k * step_us)
                ps.append(p)
    return (np.array(xs, np.uint16), np.array(ys, np.uint16), np.array(ts, np.int64),
            np.array(ps, np.int8))


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_equal_timestamps_along_edges(variant):
    """A whole edge shares one timestamp (flat along the edge): finite, and where there is
    enough history the explicit fits recover the 20 px/s normal flow exactly."""
    x, y, t, p = step_square_events()
    for window_us in (40_000, 50_000, 120_000):  # only the current step / one / two steps back
        idx, vx, vy = run_kernel(x, y, t, p, 40, 40, variant=variant, window_us=window_us)
        ref = run_naive(x, y, t, p, 40, 40, variant=variant, window_us=window_us)
        np.testing.assert_array_equal(idx, ref[0])
        assert np.isfinite(vx).all() and np.isfinite(vy).all()
        if window_us == 40_000:
            assert len(idx) == 0  # one timestamp per polarity in the window: no gradient
    if variant in ("single", "iterative", "robust"):
        idx, vx, vy = run_kernel(x, y, t, p, 40, 40, variant=variant, window_us=120_000)
        sp = np.hypot(vx, vy)
        assert np.median(sp) == pytest.approx(20.0, rel=1e-6)


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_flash_flat_surface_gives_no_flow(variant):
    """Every pixel of a block fires at one time: g = 0, infinite speed, rejected."""
    ys, xs = np.mgrid[2:12, 2:12]
    x, y = xs.ravel(), ys.ravel()
    t = np.full(len(x), 5000)
    idx, vx, vy = run_kernel(x, y, t, np.ones(len(x)), 14, 14, variant=variant,
                             max_speed=1e300)
    assert len(idx) == 0


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_collinear_and_too_few_points(variant):
    # a single row of pixels firing one after another: points collinear in x-y
    x = np.arange(2, 18)
    y = np.full(len(x), 5)
    t = 1000 * np.arange(1, len(x) + 1)
    idx, vx, vy = run_kernel(x, y, t, np.ones(len(x)), 20, 10, variant=variant)
    assert len(idx) == 0
    # two events only
    idx, _, _ = run_kernel([5, 6], [5, 5], [10, 20], [1, 1], 10, 10, variant=variant)
    assert len(idx) == 0


def test_fit_explicit_detects_singular_normal_equations():
    X = np.array([0.0, 1.0, 2.0, 3.0])
    Y = 2 * X  # on a line
    T = np.array([0.0, 0.1, 0.2, 0.3])
    ok, *_ = fit_explicit(X, Y, T, np.ones(4, np.bool_), 4)
    assert not ok
    ok, a, b, c = fit_explicit(np.array([0.0, 1, 0]), np.array([0.0, 0, 1]),
                               np.array([0.0, 0.01, 0.02]), np.ones(3, np.bool_), 3)
    assert ok and a == pytest.approx(0.01) and b == pytest.approx(0.02) and c == pytest.approx(0)


def test_window_edge_is_inclusive():
    """A neighbour exactly window_us old counts, one µs older does not."""
    # (4, 5) and (5, 4) at t0, (6, 6) at 9 ms, the centre (5, 5) last at 10 ms
    x = [4, 5, 6, 5]
    y = [5, 4, 6, 5]
    for age, expect in ((8_000, [3]), (8_001, [])):
        t = [10_000 - age, 10_000 - age, 9_000, 10_000]
        idx, vx, vy = run_kernel(x, y, t, np.ones(4), 11, 11, window_us=8_000, r=1,
                                 max_speed=1e6)
        assert list(idx) == expect
        ref = run_naive(x, y, t, np.ones(4), 11, 11, window_us=8_000, r=1, max_speed=1e6)
        assert np.array_equal(idx, ref[0])


@pytest.mark.parametrize("variant", FITTING)
def test_border(variant):
    g = Geometry(40, 32)
    ev = moving_edge_events(50.0, 20.0, g, duration_us=1_500_000)
    idx, _, _ = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, variant=variant,
                           window_us=100_000, r=2)
    xs, ys = ev.x[idx], ev.y[idx]
    assert xs.min() >= 2 and ys.min() >= 2 and xs.max() <= 37 and ys.max() <= 29
    idx0, vx, vy = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, variant=variant,
                              window_us=100_000, r=2, margin=0)
    assert np.isfinite(vx).all() and np.isfinite(vy).all()
    if variant == "savitzky_golay":
        assert np.array_equal(idx0, idx)  # SG needs the full stencil anyway
    else:
        assert len(idx0) > len(idx)
        assert ev.x[idx0].min() == 0 or ev.y[idx0].min() == 0


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_polarities_are_independent(variant):
    """An ON edge and an OFF edge interleaved over the same pixels give exactly the flow each
    gives alone."""
    g = Geometry(32, 24)
    on = moving_edge_events(80.0, 30.0, g, duration_us=500_000, polarity=1)
    off = moving_edge_events(-40.0, 60.0, g, duration_us=500_000, polarity=-1)
    x = np.concatenate([on.x, off.x])
    y = np.concatenate([on.y, off.y])
    t = np.concatenate([on.t, off.t])
    p = np.concatenate([on.p, off.p])
    o = np.argsort(t, kind="stable")
    kw = dict(variant=variant, window_us=100_000)
    both = run_kernel(x[o], y[o], t[o], p[o], g.width, g.height, **kw)
    alone_on = run_kernel(on.x, on.y, on.t, on.p, g.width, g.height, **kw)
    alone_off = run_kernel(off.x, off.y, off.t, off.p, g.width, g.height, **kw)
    is_on = o[both[0]] < len(on.t)
    np.testing.assert_array_equal(both[1][is_on], alone_on[1])
    np.testing.assert_array_equal(both[1][~is_on], alone_off[1])
    np.testing.assert_array_equal(both[2][~is_on], alone_off[2])


def test_refractory_updates_memory_but_skips_flow():
    """jAER semantics: an event within the refractory period of the previous one at the same
    pixel and polarity gets no flow but still updates the surface."""
    # L-shaped history, then the centre fires twice 1 ms apart
    x = [4, 5, 5, 5]
    y = [5, 4, 5, 5]
    t = [1000, 2000, 3000, 4000]
    idx, _, _ = run_kernel(x, y, t, np.ones(4), 11, 11, r=1, refractory_us=1500,
                           max_speed=1e6)
    assert list(idx) == [2]
    idx, _, _ = run_kernel(x, y, t, np.ones(4), 11, 11, r=1, refractory_us=500,
                           max_speed=1e6)
    assert list(idx) == [2, 3]


def test_refractory_without_update_keeps_the_onset():
    """refractory_updates false (the thesis's description): a refractory event neither gets
    flow nor updates the surface, and the period counts from the last event that did."""
    # L-shaped history, then the centre fires at 3, 4 and 4.6 ms
    x = [4, 5, 5, 5, 5]
    y = [5, 4, 5, 5, 5]
    t = [1000, 2000, 3000, 4000, 4600]
    kw = dict(r=1, refractory_us=1500, max_speed=1e6)
    idx, _, _ = run_kernel(x, y, t, np.ones(5), 11, 11, **kw)
    assert list(idx) == [2]  # jAER: 4.6 ms is 0.6 ms after the (refractory) 4 ms event
    idx, _, _ = run_kernel(x, y, t, np.ones(5), 11, 11, refractory_updates=False, **kw)
    assert list(idx) == [2, 4]  # 4.6 ms is 1.6 ms after the onset at 3 ms
    ref = run_naive(x, y, t, np.ones(5), 11, 11, refractory_updates=False, **kw)
    assert list(ref[0]) == [2, 4]
    # the surface kept 3 ms at the centre: a neighbour's fit sees it, not 4 ms
    g = Geometry(24, 20)
    ev = random_events(1500, g, 0, 150_000, seed=13)
    for variant in VARIANTS:
        assert_same(ev, g.width, g.height, variant=variant, refractory_us=20_000,
                    refractory_updates=False, th2=0.02, centre_check=True)


@pytest.mark.parametrize("size", [3, 5, 7])
def test_sg_mask_tables_match_pairwise_slopes(size):
    """The tabulated Savitzky-Golay slopes equal the pairwise sums for random validity masks."""
    from evchain.kernels.plane_flow import sg_gradient, sg_gradient_masks, sg_tables

    coef, pairs = sg_tables(size)
    rng = np.random.default_rng(size)
    for _ in range(300):
        wv = (rng.random(size * size) < rng.uniform(0.1, 1.0)).astype(np.float64)
        wt = -rng.integers(0, 80_000, size * size).astype(np.float64) * wv
        grid = wv.reshape(size, size).astype(np.int64)
        rowmask = (grid << np.arange(size)).sum(1)
        colmask = (grid << np.arange(size)[:, None]).sum(0)
        ref = sg_gradient(wt, wv, size)
        got = sg_gradient_masks(wt, rowmask, colmask, size, coef, pairs)
        assert got[0] == ref[0]
        np.testing.assert_allclose(got[1:], ref[1:], rtol=1e-12, atol=1e-18)


# ------------------------------------------------------------------ speed-adaptive window


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("refit_failed", [False, True])
def test_adaptive_window_random_stream_matches_reference(variant, refit_failed):
    g = Geometry(24, 20)
    ev = random_events(1500, g, 0, 400_000, seed=12)
    kw = dict(variant=variant, refractory_us=3000, window_us=20_000, max_window_us=150_000,
              slow_px=2.5, refit_failed=refit_failed, centre_check=True, th2=0.01)
    got = assert_same(ev, g.width, g.height, **kw)
    assert len(got[0]) > 20
    if variant != "original":  # the refits change the result (the comparison is not vacuous)
        off = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, **{**kw, "max_window_us": 0})
        assert not np.array_equal(off[0], got[0])


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("r", [2, 4])  # 4: Savitzky-Golay without the mask tables
def test_adaptive_loop_without_refits_equals_fixed_loop(variant, r):
    """The loop is compiled twice (with and without the refits): with no window to grow to,
    the adaptive copy gives exactly the fixed copy's flow and surface."""
    g = Geometry(24, 20)
    ev = random_events(3000, g, 0, 400_000, seed=5)
    args = (ev.x, ev.y, ev.t, ev.p)
    prm = record(PlaneParams, variant=VARIANTS[variant], r=r, window_us=20_000,
                 refractory_us=3000, margin=r, min_points=3, th1=1e-5, th2=0.01, max_speed=1e4,
                 max_iter=10, min_spread=0.3, centre_check=True, max_window_us=20_000,
                 slow_px=2.0, refit_failed=False, refractory_updates=True, min_window_us=0,
                 fast_px=4.0)
    out = []
    for kernel in (plane_flow_kernel, plane_flow_adaptive_kernel):
        ts = new_state(g.width, g.height)
        idx, vx, vy = np.empty(len(ev), np.int64), np.empty(len(ev)), np.empty(len(ev))
        counts = np.zeros(len(WHY_NO_FLOW) + 1, np.int64)
        k = kernel(*args, ts, prm, idx, vx, vy, counts)
        out.append((idx[:k], vx[:k], vy[:k], ts, counts))
    assert len(out[0][0]) > 20
    for a, b in zip(out[0], out[1], strict=True):
        np.testing.assert_array_equal(a, b)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), variant=st.sampled_from(list(VARIANTS)),
       r=st.integers(1, 3), window_us=st.integers(5_000, 100_000),
       max_window_us=st.integers(0, 400_000), slow_px=st.sampled_from([0.5, 2.0, 3.0, 6.0]),
       refit_failed=st.booleans(), refractory_us=st.integers(0, 40_000),
       refractory_updates=st.booleans(), th2=st.sampled_from([1e-3, 1e-2, 5e-2]),
       centre_check=st.booleans())
def test_adaptive_window_random_parameters_match_reference(seed, variant, r, window_us,
                                                           max_window_us, slow_px,
                                                           refit_failed, refractory_us,
                                                           refractory_updates, th2,
                                                           centre_check):
    g = Geometry(16, 14)
    ev = random_events(500, g, 0, 300_000, seed=seed)
    assert_same(ev, g.width, g.height, variant=variant, r=r, window_us=window_us,
                max_window_us=max_window_us, slow_px=slow_px, refit_failed=refit_failed,
                refractory_us=refractory_us, refractory_updates=refractory_updates, th2=th2,
                max_speed=200.0, centre_check=centre_check)


@pytest.mark.parametrize("variant", FITTING)
@pytest.mark.parametrize("ang", ANGLES)
def test_adaptive_window_slow_edge(variant, ang):
    """A 5 px/s edge (incl. edges along an axis) with an 80 ms window moves 0.4 px within it:
    the fixed window gives (almost) no flow; the adaptive one (up to 1 s, 2 px) gives the
    velocity on most events, same as the reference."""
    g = Geometry(40, 32)
    speed = 5.0
    vx, vy = speed * np.cos(np.radians(ang)), speed * np.sin(np.radians(ang))
    ev = moving_edge_events(vx, vy, g, duration_us=int(40 / speed * 1e6))
    kw = dict(variant=variant, window_us=80_000, th2=0.2 / speed, max_speed=1e5,
              centre_check=True)
    fixed = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, **kw)
    kw.update(max_window_us=1_000_000, slow_px=2.0)
    idx, ex, ey = assert_same(ev, g.width, g.height, **kw)
    assert len(fixed[0]) < 0.1 * len(ev)
    assert len(idx) >= 0.7 * len(ev), (len(idx), len(ev))
    err = np.hypot(ex - vx, ey - vy) / speed
    assert err.max() < 0.03, (variant, ang, err.max())


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_adaptive_window_leaves_fast_edges_and_off_unchanged(variant):
    """An edge moving more than slow_px within window_us is never refitted; max_window_us
    <= window_us is off: both bit-identical to the fixed window."""
    g = Geometry(40, 32)
    ev = moving_edge_events(100.0, 30.0, g, duration_us=400_000)
    kw = dict(variant=variant, window_us=40_000, refit_failed=False)
    ref = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, **kw)
    assert len(ref[0]) > 0 or variant == "original"
    for extra in (dict(max_window_us=400_000, slow_px=2.0), dict(max_window_us=40_000),
                  dict(max_window_us=10_000, refit_failed=True)):
        got = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, **{**kw, **extra})
        for a, b in zip(ref, got, strict=True):
            np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------ short window for fast edges


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), variant=st.sampled_from(list(VARIANTS)),
       r=st.integers(1, 3), window_us=st.integers(5_000, 100_000),
       min_window_us=st.integers(1, 60_000), fast_px=st.sampled_from([0.5, 2.0, 4.0]),
       max_window_us=st.sampled_from([0, 200_000]), refit_failed=st.booleans(),
       refractory_us=st.integers(0, 40_000), th2=st.sampled_from([1e-3, 1e-2, 5e-2]),
       centre_check=st.booleans())
def test_short_window_random_parameters_match_reference(seed, variant, r, window_us,
                                                        min_window_us, fast_px, max_window_us,
                                                        refit_failed, refractory_us, th2,
                                                        centre_check):
    g = Geometry(16, 14)
    ev = random_events(500, g, 0, 300_000, seed=seed)
    assert_same(ev, g.width, g.height, variant=variant, r=r, window_us=window_us,
                min_window_us=min_window_us, fast_px=fast_px, max_window_us=max_window_us,
                refit_failed=refit_failed, refractory_us=refractory_us, th2=th2,
                max_speed=1e5, centre_check=centre_check)


def two_edges(vx, vy, g, gap_us, duration_us):
    """An edge and the same edge ``gap_us`` later (one polarity): texture whose second edge
    finds the first one's timestamps within a long window."""
    ev = moving_edge_events(vx, vy, g, duration_us=duration_us)
    t = np.r_[ev.t, ev.t + gap_us]
    o = np.argsort(t, kind="stable")
    keep = t[o] < duration_us
    return (np.r_[ev.x, ev.x][o][keep], np.r_[ev.y, ev.y][o][keep], t[o][keep],
            np.r_[ev.p, ev.p][o][keep])


@pytest.mark.parametrize("variant", FITTING)
@pytest.mark.parametrize("ang", ANGLES)
def test_short_window_fast_edges_match_reference(variant, ang):
    """Fast edges in 8 directions (along the axes too) followed by a second edge: kernel =
    reference with the short window, the median flow event within 3 % of the velocity."""
    g = Geometry(40, 32)
    speed = 300.0
    vx, vy = speed * np.cos(np.radians(ang)), speed * np.sin(np.radians(ang))
    x, y, t, p = two_edges(vx, vy, g, 40_000, 120_000)
    ev = SimpleNamespace(x=x, y=y, t=t, p=p)
    kw = dict(variant=variant, window_us=80_000, th2=0.004, max_speed=1e5, centre_check=True,
              max_window_us=500_000)
    idx, ex, ey = assert_same(ev, g.width, g.height, **kw, min_window_us=5_000, fast_px=4.0)
    assert len(idx) > 0.3 * len(t)
    err = np.hypot(ex - vx, ey - vy) / speed
    assert np.median(err) < 0.03, (variant, ang, np.median(err))


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_short_window_hard_inputs(variant):
    """Flat surfaces, an axis edge too fast for any window (3 µs per column), a line, one
    pixel, timestamps across the 32-bit wrap point: finite output, kernel = reference."""
    g = Geometry(20, 16)
    ys, xs = np.mgrid[0:g.height, 0:g.width]
    cases = {"flat": (xs.ravel(), ys.ravel(), np.full(xs.size, 1000)),
             "huge_speed": (xs.ravel(), ys.ravel(), (xs * 3).ravel()),
             "axis_fast": (xs.ravel(), ys.ravel(), (xs * 2000).ravel()),
             "line": (np.arange(14), np.arange(14), np.arange(14) * 1000),
             "one_pixel": (np.full(50, 9), np.full(50, 8), np.arange(50) * 100),
             # across the point where 32-bit µs timestamps wrap (int64 here: no wrap)
             "wrap32": (xs.ravel(), ys.ravel(), (np.int64(1) << 32) - 20_000
                        + (xs * 2000).ravel())}
    for name, (x, y, t) in cases.items():
        o = np.argsort(t, kind="stable")
        ev = SimpleNamespace(x=x[o], y=y[o], t=t[o], p=np.ones(len(t), np.int8))
        idx, vx, vy = assert_same(ev, g.width, g.height, variant=variant, window_us=80_000,
                                  min_window_us=2_000, fast_px=4.0, max_speed=1e7,
                                  centre_check=True, th2=0.004)
        if name in ("flat", "line", "one_pixel"):
            assert len(idx) == 0, name


@pytest.mark.parametrize("variant", FITTING)
def test_short_window_random_stream_matches_reference(variant):
    """A random stream with the short window: kernel = reference, and the short refits change
    the output (the comparison is not vacuous)."""
    g = Geometry(24, 20)
    ev = random_events(1500, g, 0, 400_000, seed=12)
    kw = dict(variant=variant, refractory_us=3000, window_us=40_000, max_window_us=150_000,
              slow_px=2.5, centre_check=True, th2=0.01)
    got = assert_same(ev, g.width, g.height, **kw, min_window_us=2_000, fast_px=1.0)
    off = run_kernel(ev.x, ev.y, ev.t, ev.p, g.width, g.height, **kw)
    assert len(off[0]) != len(got[0]) or not np.array_equal(off[1], got[1])
