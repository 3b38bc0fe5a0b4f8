"""ttc recovers a known time to contact; region B and hard inputs; kernel vs reference."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.series import FOE as FOE_SERIES
from evchain.filters.foe_map import FoeMap, foe_series
from evchain.filters.ttc import Ttc
from evchain.testing.contract import check_filter
from evchain.testing.synthetic import expansion_stream
from tests.naive.foe_map import expansion_packets
from tests.naive.ttc import PX, baseline_tau_naive, event_tau_naive, ground_constant_naive

G = Geometry(128, 96, f=100.0)
FOE = (60.0, 40.0)


def with_true_foe(packets, foe=FOE):
    return [p.with_series("foe", foe_series([foe[0]], [foe[1]], [p.t_start], [1.0]))
            for p in packets]


def run_ttc(packets, **params):
    # the random-point fields below have exact flow but no moving edges: tau from the flow
    params.setdefault("baseline_px", 0)
    params = {**PX, **params}
    f = Ttc()
    f.setup(Ttc.Params(**params), Context())
    return FlowPacket.concat([f.process(p) for p in packets])


def approach(tau0=3.0, duration_us=2_000_000, n=150_000, **opts):
    return expansion_packets(foe=FOE, tau_s=tau0, n=n, geometry=G, duration_us=duration_us,
                             n_packets=10, tau_shrinks=True, **opts)


def rel_errors(out, tau0=3.0):
    s = out.series["ttc"]
    assert len(s) > 0 and np.isfinite(s["tau_s"]).all()
    truth = tau0 - s["t"] * 1e-6
    return np.abs(s["tau_s"] - truth) / truth


NOISY = dict(normal_only=True, noise_frac=0.2, outlier_frac=0.1)
# (generator options, foe_map instead of the true FOE, ttc params, median tolerance,
#  share within 10 %)
RECOVERY = {
    "full flow, true FOE": (dict(), False, {}, 0.02, 0.95),
    "normal flow, true FOE": (dict(normal_only=True), False, {}, 0.02, 0.95),
    "normal flow + noise + outliers, foe_map": (NOISY, True, {}, 0.09, 0.6),
    "same, most active cluster": (NOISY, True, {"select": "support"}, 0.06, 0.85),
}


@pytest.mark.parametrize("name", list(RECOVERY))
def test_recovers_ttc(name):
    opts, use_map, params, med_tol, share = RECOVERY[name]
    packets = approach(**opts)
    if use_map:
        fm = FoeMap()
        fm.setup(FoeMap.Params(), Context())
        packets = [fm.process(p) for p in packets]
    else:
        packets = with_true_foe(packets)
    rel = rel_errors(run_ttc(packets, **params))
    assert np.median(rel) <= med_tol, np.median(rel)
    assert np.mean(rel <= 0.10) >= share


@pytest.mark.parametrize("w", [(0.1, 0.0, 0.0), (0.0, 0.25, 0.0), (0.05, -0.1, 0.02)])
def test_recovers_ttc_under_rotation(w):
    """The camera turns (pitch 0.1 rad/s: 10 px/s at the principal point, the car's flow near
    the FOE a few px/s): with its angular velocity in the FOE entries the rotational flow is
    taken off each event's normal flow, and the TTC is as good as without rotation; the same
    flow with entries that carry no rotation gives a wrong one."""
    packets = approach(normal_only=True)
    X = [(p.x.astype(float) - G.cx) / G.f for p in packets]
    Y = [(p.y.astype(float) - G.cy) / G.f for p in packets]
    turned = []
    for p, x, y in zip(packets, X, Y, strict=True):
        u = G.f * (x * y * w[0] - (1 + x * x) * w[1] + y * w[2])
        v = G.f * ((1 + y * y) * w[0] - x * y * w[1] - x * w[2])
        s = np.hypot(p.vx, p.vy)
        n = (p.vx / np.where(s > 0, s, 1), p.vy / np.where(s > 0, s, 1))
        r = n[0] * u + n[1] * v  # normal flow: the rotation's normal component
        turned.append(p.replace(vx=(p.vx + r * n[0]).astype(np.float32),
                                vy=(p.vy + r * n[1]).astype(np.float32)))
    errors = []
    for flag in (1, 0):
        foe = [p.with_series("foe", FOE_SERIES.array(
            t=[p.t_start], x=[FOE[0]], y=[FOE[1]], support=[1.0], total=[1.0],
            wx_deg_s=[np.degrees(w[0])], wy_deg_s=[np.degrees(w[1])],
            wz_deg_s=[np.degrees(w[2])], rotation=[flag])) for p in turned]
        out = run_ttc(foe)
        errors.append(np.median(rel_errors(out)) if len(out.series["ttc"]) else np.inf)
    assert errors[0] <= 0.02, errors
    assert errors[1] > 5 * errors[0], errors


def test_tau_falls_one_second_per_second_without_updates():
    packets = with_true_foe(approach(duration_us=1_000_000, n=80_000))
    quiet = FlowPacket.empty(G, 1_000_000, 1_100_000)
    out = run_ttc(packets + [quiet], activity_tau_ms=400.0, min_activity=1.0)
    s = out.series["ttc"]
    late = s[s["t"] >= 1_000_000]
    assert len(late) >= 3
    # prediction: -1 s/s exactly between ticks
    np.testing.assert_allclose(np.diff(late["tau_s"]), -np.diff(late["t"]) * 1e-6, atol=1e-9)


def test_nothing_before_a_foe():
    out = run_ttc(approach(duration_us=200_000, n=10_000))
    assert len(out.series["ttc"]) == 0


def test_empty_region_b():
    # FOE at the bottom row: nothing is below it
    packets = with_true_foe(approach(duration_us=300_000, n=20_000), foe=(60.0, 95.5))
    out = run_ttc(packets)
    assert len(out.series["ttc"]) == 0 and len(out.series["ttc_clusters"]) == 0


def hard_flow(vx, vy, x, y, n=400):
    rng = np.random.default_rng(0)
    return FlowPacket(geometry=G, t_start=0, t_end=100_000, x=np.full(n, x, np.uint16),
                      y=np.full(n, y, np.uint16), t=np.sort(rng.integers(0, 100_000, n)),
                      p=np.ones(n, np.int8), vx=np.full(n, vx, np.float32),
                      vy=np.full(n, vy, np.float32))


@pytest.mark.parametrize("case", [(0.0, 0.0, 70, 60), (0.0, 30.0, 60, 70), (25.0, 0.0, 80, 60),
                                  (10.0, 10.0, 60, 40), (1e-30, 0.0, 70, 60)])
def test_hard_inputs_are_finite(case):
    vx, vy, x, y = case
    out = run_ttc(with_true_foe([hard_flow(vx, vy, x, y)]), min_speed_pxs=0.0)
    s = out.series["ttc"]
    assert np.isfinite(s["tau_s"]).all()
    if (x, y) == FOE or (vx, vy) == (0.0, 0.0):
        assert len(s) == 0       # zero flow or an event at the FOE: no tau at all
    if (vx, vy, x, y) == (0.0, 30.0, 60, 70):  # flow along y, straight below the FOE
        np.testing.assert_allclose(s["tau_s"][0], 1.0, rtol=0.05)


def test_event_tau_matches_reference():
    from evchain.kernels.ttc import event_tau

    rng = np.random.default_rng(1)
    n = 3000
    px, py = rng.integers(0, 128, n).astype(float), rng.integers(0, 96, n).astype(float)
    vx, vy = rng.normal(0, 50, n), rng.normal(0, 50, n)
    vx[::7] = 0.0
    vy[::5] = 0.0
    args = (60.0, 40.0, 30.0, 2.0, 8.0, 1.0, 500.0, 0.05, 20.0)
    want = event_tau_naive(px, py, vx, vy, *args)
    f = Ttc()
    f.setup(Ttc.Params(region_b_half_width_px=30.0, region_b_min_below_px=2.0,
                       min_distance_px=8.0, min_speed_pxs=1.0, max_speed_pxs=500.0,
                       min_tau_s=0.05, max_tau_s=20.0), Context())
    got = np.array([event_tau(px[i], py[i], vx[i], vy[i], 60.0, 40.0, f._constants(G))
                    for i in range(n)])
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert (want > 0).sum() > 50


def test_contract():
    packets, truth = expansion_stream(foe_series=True)
    ref = check_filter(Ttc, {**PX, "estimate_every_us": 5000, "min_samples": 3, "baseline_px": 0},
                       packets, truth=truth)
    assert len(ref["series:ttc"]) > 5


def road_and_obstacle(tau0=3.0, k_road=40.0, duration_us=1_000_000, n_road=60_000,
                      n_obs=15_000, n_packets=10, seed=3):
    """Region B filled with road (tau * dy = k_road, dy = rows below the FOE) plus an obstacle
    patch off to the side and nearer the horizon (one tau for all its points, falling 1 s/s,
    so tau * dy < k_road: nearer than the road at its rows); full flow with 2 % noise. A road
    point straight below the FOE is nearer the FOE than the obstacle."""
    rng = np.random.default_rng(seed)
    fx, fy = FOE
    rx = np.concatenate([rng.uniform(-55, 55, n_road), rng.uniform(25, 40, n_obs)])
    ry = np.concatenate([rng.uniform(10, 54, n_road), rng.uniform(4, 12, n_obs)])
    t = np.concatenate([rng.integers(0, duration_us, n_road), rng.integers(0, duration_us, n_obs)])
    road = np.arange(rx.size) < n_road
    x, y = np.round(fx + rx), np.round(fy + ry)
    tau = np.where(road, k_road / (y - fy), tau0 - t * 1e-6)
    noise = 1.0 + 0.02 * rng.standard_normal((2, rx.size))
    vx, vy = (x - fx) / tau * noise[0], (y - fy) / tau * noise[1]
    o = np.argsort(t, kind="stable")
    cuts = np.linspace(0, duration_us, n_packets + 1).astype(np.int64)
    idx = np.searchsorted(t[o], cuts)
    return [FlowPacket(geometry=G, t_start=int(cuts[k]), t_end=int(cuts[k + 1]),
                       x=x[o][idx[k]:idx[k + 1]].astype(np.uint16),
                       y=y[o][idx[k]:idx[k + 1]].astype(np.uint16), t=t[o][idx[k]:idx[k + 1]],
                       p=np.ones(idx[k + 1] - idx[k], np.int8),
                       vx=vx[o][idx[k]:idx[k + 1]].astype(np.float32),
                       vy=vy[o][idx[k]:idx[k + 1]].astype(np.float32))
            for k in range(n_packets)]


@pytest.mark.parametrize("ground", [False, True])
def test_ground_plane_test_selects_the_obstacle(ground):
    packets = with_true_foe(road_and_obstacle())
    f = Ttc()
    # random points (tau from the flow); large clusters, as the scenario was built for
    f.setup(Ttc.Params(**{**PX, "max_cluster_size_px": 60.0}, ground_test=ground, baseline_px=0),
            Context())
    out = FlowPacket.concat([f.process(p) for p in packets])
    s = out.series["ttc"]
    s = s[s["t"] >= 500_000]
    assert len(s) > 10 and np.isfinite(s["tau_s"]).all()
    truth = 3.0 - s["t"] * 1e-6
    rel = np.median(np.abs(s["tau_s"] - truth) / truth)
    if ground:   # the road is recognised (K = 40 s px found) and the obstacle is selected
        from evchain.kernels.ttc import ground_constant

        np.testing.assert_allclose(ground_constant(f._state), 40.0, rtol=0.05)
        assert rel < 0.05, rel
        cl = out.series["ttc_clusters"]
        key = cl["t"] * 10_000 + cl["cluster"]
        rho = cl["ground_ratio"][np.isin(key, s["t"] * 10_000 + s["cluster"])]
        assert len(rho) == len(s) and ((rho >= 0) & (rho < 0.8)).all(), rho
    else:        # the road cluster nearest the FOE wins and its tau is k_road / dy, not 3 - t
        assert rel > 0.2, rel


def _ground_run(kg, t, tol, memory_us):
    from evchain.kernels.ttc import ground_mode, ground_vote, new_state

    state = new_state(1, 4, 0, 0, False)
    h = state.ground_hist
    for v, ti in zip(kg, t, strict=True):
        ground_vote(h, state.carry, v, float(ti), memory_us)
    half = int(round(np.log(1.0 + tol) / 0.02))
    return ground_mode(h, half), state.carry["n_votes"][0]


@pytest.mark.parametrize("seed", [0, 1])
def test_ground_constant_matches_reference(seed):
    rng = np.random.default_rng(seed)
    n = 4000
    kg = rng.lognormal(np.log(40.0), 0.3, n)
    kg[rng.random(n) < 0.3] *= 0.4               # obstacle-like events, below the road
    kg[::97] = 0.0
    kg[::89] = -5.0
    kg[::101] = np.nan
    kg[::103] = np.inf
    kg[1000:1010] = 1e6                          # outliers
    kg[2000:2005] = 0.01                         # the histogram's lowest bin, and below it
    kg[2005:2010] = 0.0099
    kg[3000:3005] = 1e12                         # beyond its highest bin
    # times with long gaps: the kernel's weights overflow and get rescaled
    t = np.cumsum(rng.exponential(1.0, n) * np.where(rng.random(n) < 0.01, 3e8, 2e3))
    for tol, memory_us in ((0.1, 1e6), (0.05, 2e5), (0.3, 5e7)):
        k, nv = _ground_run(kg, t, tol, memory_us)
        want_k, want_n = ground_constant_naive(kg, t, tol, memory_us)
        np.testing.assert_allclose(k, want_k, rtol=1e-9)
        assert nv == want_n
    assert _ground_run(np.array([np.nan, -1.0, 0.0]), np.arange(3.0), 0.1, 1e6) == (0.0, 0.0)


def test_ground_constant_leaves_a_wrong_start():
    """A mode seen first (here half the road's K, as from events while the FOE is still far
    off) is left once the road's votes outweigh it: K follows the road within one bin."""
    rng = np.random.default_rng(5)
    first = rng.lognormal(np.log(20.0), 0.05, 2000)          # a wrong start, for 0.2 s
    road = rng.lognormal(np.log(40.0), 0.05, 20000)          # then the road, for 2 s
    kg = np.concatenate([first, road])
    t = np.concatenate([np.linspace(0, 2e5, first.size), np.linspace(2e5, 2.2e6, road.size)])
    k, _ = _ground_run(kg[:first.size], t[:first.size], 0.1, 1e6)
    np.testing.assert_allclose(k, 20.0, rtol=0.02)
    k, _ = _ground_run(kg, t, 0.1, 1e6)
    np.testing.assert_allclose(k, 40.0, rtol=0.02)


def test_ground_plane_contract():
    packets = with_true_foe(road_and_obstacle(duration_us=300_000, n_road=12_000, n_obs=3_000,
                                              n_packets=4))
    ref = check_filter(Ttc, {**PX, "ground_test": True, "ground_min_events": 50,
                             "select_hold": True, "corridor_half_width_h": 2.0,
                             "baseline_px": 0}, packets)
    assert len(ref["series:ttc"]) > 5


# -- tau from a long baseline (positions and times of moving edges) -------------------------

def edge_approach(tc=3.0, duration_s=2.0, speed_factor=1.0, jitter_us=0.0, seed=0):
    """Events of a frontal rectangle approaching at constant speed (contact at ``tc``) below
    the FOE: its image offsets grow as R / (tc - t). Each edge fires one event per pixel when
    it crosses the pixel's centre; the flow is the edge's true normal flow times
    ``speed_factor`` (2: measured twice too fast, like a short flow window on slow edges)."""
    rng = np.random.default_rng(seed)
    fx, fy = FOE
    xl, xr, yt, yb = -30.0, 30.0, 6.0, 30.0   # offsets at tau = 1 s
    ev = []
    for c in range(G.width):              # vertical edges, flow along x
        for xe, pol in ((xl, 0), (xr, 1)):
            r = c - fx
            if r * xe <= 0:
                continue
            tau = xe / r
            t = tc - tau
            if 0 <= t < duration_s:
                for row in range(int(np.ceil(fy + yt / tau)), int(np.floor(fy + yb / tau)) + 1):
                    if 0 <= row < G.height:
                        ev.append((c, row, t, 2 * pol - 1, speed_factor * r / tau, 0.0))
    for row in range(G.height):           # horizontal edges, flow along y
        for ye, pol in ((yt, 0), (yb, 1)):
            r = row - fy
            if r <= 0:
                continue
            tau = ye / r
            t = tc - tau
            if 0 <= t < duration_s:
                for c in range(int(np.ceil(fx + xl / tau)), int(np.floor(fx + xr / tau)) + 1):
                    if 0 <= c < G.width:
                        ev.append((c, row, t, 2 * pol - 1, 0.0, speed_factor * r / tau))
    a = np.array(ev)
    a[:, 2] = np.clip(a[:, 2] * 1e6 + rng.normal(0, jitter_us, len(a)) if jitter_us else
                      a[:, 2] * 1e6, 0, duration_s * 1e6 - 1)
    return _packets(a, duration_s)


def _packets(a, duration_s):
    """Ten flow packets of the rows (x, y, t µs, p, vx, vy[, t_edge µs]) of ``a``."""
    a = a[np.argsort(a[:, 2], kind="stable")]
    bounds = np.linspace(0, duration_s * 1e6, 11).astype(np.int64)
    idx = np.searchsorted(a[:, 2], bounds)
    return [FlowPacket(geometry=G, t_start=int(b0), t_end=int(b1),
                       x=a[i:j, 0].astype(np.uint16), y=a[i:j, 1].astype(np.uint16),
                       t=a[i:j, 2].astype(np.int64), p=a[i:j, 3].astype(np.int8),
                       vx=a[i:j, 4].astype(np.float32), vy=a[i:j, 5].astype(np.float32),
                       t_edge=a[i:j, 6].astype(np.int64) if a.shape[1] > 6 else None
                       ).validate()
            for b0, b1, i, j in zip(bounds[:-1], bounds[1:], idx[:-1], idx[1:], strict=True)]


@pytest.mark.parametrize("speed_factor", [1.0, 2.0])
@pytest.mark.parametrize("jitter_us", [0.0, 5_000.0])
def test_baseline_recovers_ttc_of_slow_edges(speed_factor, jitter_us):
    packets = with_true_foe(edge_approach(speed_factor=speed_factor, jitter_us=jitter_us))
    s = run_ttc(packets, baseline_px=6, min_samples=4).series["ttc"]
    s = s[s["t"] >= 500_000]
    assert len(s) > 50 and np.isfinite(s["tau_s"]).all()
    truth = 3.0 - s["t"] * 1e-6
    rel = np.abs(s["tau_s"] - truth) / truth
    assert np.median(rel) <= 0.05, np.median(rel)
    assert np.mean(rel <= 0.10) >= 0.9
    if speed_factor == 2.0:  # the flow's magnitude alone is off by the factor
        s0 = run_ttc(packets, min_samples=4).series["ttc"]
        s0 = s0[s0["t"] >= 500_000]
        truth0 = 3.0 - s0["t"] * 1e-6
        assert np.median(np.abs(s0["tau_s"] - truth0) / truth0) > 0.3


def edge_approach_in_runs(tc=3.0, duration_s=2.0, seed=0):
    """:func:`edge_approach`'s rectangle with two events per edge crossing, as a rendered edge
    stepping over a pixel's two sample lines fires them: when it passes a quarter pixel before
    and after the pixel's centre. The flow stage keeps one of the two at random, at some
    pixels both; ``t_edge`` is the first one's time (the run's start) either way."""
    rng = np.random.default_rng(seed)
    fx, fy = FOE
    xl, xr, yt, yb = -30.0, 30.0, 6.0, 30.0
    ev = []

    def crossing(c, row, r, e, pol, along_x):
        times = [tc - e / (r - 0.25 * np.sign(r)), tc - e / (r + 0.25 * np.sign(r))]
        if not (0 <= times[0] and times[1] < duration_s):
            return
        keep = rng.choice(3, p=[0.3, 0.1, 0.6])   # 0: the first, 1: the second, 2: both
        for k, t in enumerate(times):
            if keep == 2 or keep == k:
                v = r / (tc - t)
                ev.append((c, row, t * 1e6, 2 * pol - 1, v if along_x else 0.0,
                           0.0 if along_x else v, times[0] * 1e6))

    for c in range(G.width):
        for xe, pol in ((xl, 0), (xr, 1)):
            r = c - fx
            if r * xe > 0 and abs(r) > 0.25:
                tau = xe / r
                for row in range(int(np.ceil(fy + yt / tau)), int(np.floor(fy + yb / tau)) + 1):
                    if 0 <= row < G.height:
                        crossing(c, row, r, xe, pol, True)
    for row in range(G.height):
        for ye, pol in ((yt, 0), (yb, 1)):
            r = row - fy
            if r > 0.25:
                tau = ye / r
                for c in range(int(np.ceil(fx + xl / tau)), int(np.floor(fx + xr / tau)) + 1):
                    if 0 <= c < G.width:
                        crossing(c, row, r, ye, pol, False)
    return _packets(np.array(ev), duration_s)


def test_baseline_compares_edge_arrivals_not_flow_event_times():
    """Two events per crossing, half a pixel apart, of which the flow stage keeps either: the
    pixels' last flow-event times mix early and late ones (a pixel-to-pixel time off by up to
    half of itself); their runs' starts (``t_edge``) compare like with like."""
    packets = with_true_foe(edge_approach_in_runs())

    def errors(**params):
        # baselines of a pixel or two, as for a far obstacle's slow edges
        s = run_ttc(packets, baseline_px=6, baseline_max_ms=300.0, min_samples=4,
                    **params).series["ttc"]
        s = s[(s["t"] >= 500_000) & (s["t"] < 1_200_000)]
        assert len(s) > 30 and np.isfinite(s["tau_s"]).all()
        truth = 3.0 - s["t"] * 1e-6
        return np.abs(s["tau_s"] - truth) / truth

    with_arrivals = errors()
    assert np.median(with_arrivals) <= 0.03, np.median(with_arrivals)
    assert np.mean(with_arrivals <= 0.10) >= 0.9
    own_times = errors(edge_run_px=0.0)
    assert np.median(own_times) > 2 * np.median(with_arrivals) + 0.02, np.median(own_times)


def test_a_run_longer_than_edge_run_px_uses_the_events_own_time():
    """With every t_edge far in the past (runs spanning many edges) the baseline falls back to
    the events' own times: the same series as flow packets without t_edge."""
    base = with_true_foe(edge_approach(duration_s=1.0))
    stale = [p.replace(t_edge=p.t - 100_000_000) for p in base]
    a = run_ttc(base, baseline_px=6, min_samples=4).series["ttc"]
    b = run_ttc(stale, baseline_px=6, min_samples=4, edge_run_px=5.0).series["ttc"]
    assert len(a) > 5
    np.testing.assert_array_equal(a, b)


def test_baseline_hard_inputs_are_finite():
    for case in [(0.0, 0.0, 70, 60), (0.0, 30.0, 60, 70), (25.0, 0.0, 80, 60),
                 (10.0, 10.0, 60, 40), (1e-30, 0.0, 70, 60)]:
        vx, vy, x, y = case
        out = run_ttc(with_true_foe([hard_flow(vx, vy, x, y)]), min_speed_pxs=0.0,
                      baseline_px=6)
        # one pixel only: nothing behind any event, so no tau (and no NaN)
        assert len(out.series["ttc"]) == 0
    # a single event in region B: a cluster with one sample gives no estimate
    one = edge_approach()[5]
    one = FlowPacket(geometry=G, t_start=one.t_start, t_end=one.t_end, x=one.x[:1],
                     y=one.y[:1], t=one.t[:1], p=one.p[:1], vx=one.vx[:1], vy=one.vy[:1])
    assert len(run_ttc(with_true_foe([one]), baseline_px=6).series["ttc"]) == 0


def test_baseline_tau_matches_reference():

    rng = np.random.default_rng(2)
    S = np.full((2, 96, 128), -1e300)
    S[0] = rng.integers(0, 1_000_000, (96, 128))
    S[1] = np.where(rng.random((96, 128)) < 0.3, -1e300, rng.integers(0, 1_000_000, (96, 128)))
    # a smooth field too (times rising away from the FOE: long valid walks)
    yy, xx = np.mgrid[0:96, 0:128]
    S[0, :48] = 1_000_000 - 4e6 / (np.hypot(xx - 60.0, yy - 40.0)[:48] + 5.0)
    n, got_any = 4000, 0
    for i in range(n):
        pol = i % 2
        px, py = float(rng.integers(0, 128)), float(rng.integers(0, 96))
        ang = rng.uniform(0, 2 * np.pi) if i % 3 else rng.integers(0, 4) * np.pi / 2
        nx, ny = np.cos(ang), np.sin(ang)
        d0 = float(rng.uniform(-5, 60))
        ti = float(rng.integers(500_000, 1_100_000))
        args = (px, py, nx, ny, d0, ti, int(rng.integers(1, 10)),
                float(rng.integers(1, 9e5)), int(rng.integers(0, 4)))
        turns = _angle_history(rng, 0, 1_200_000) if i % 3 == 0 else None
        rot = 0.0 if i % 3 == 1 else float(rng.normal(0, 20))
        got_any += _baseline_agrees(S, pol, args, turns, rot) > 0
    assert got_any > 200


def _angle_history(rng, t0, t1, n_max=40):
    """A random rotation history (entry times in [t0, t1], angles rad) and the newest angular
    velocity (rad/s): (times, angles, w)."""
    n = int(rng.integers(1, n_max))
    times = np.unique(rng.integers(t0, t1, n)).astype(np.float64)
    angles = np.cumsum(rng.normal(0, 0.02, (len(times), 3)), axis=0)
    return times, angles, rng.normal(0, 0.3, 3)


def _baseline_agrees(S, pol, args, turns=None, rot=0.0, f=150.0, cx=60.0, cy=45.0) -> float:
    """The kernel's baseline tau equals the reference's (finite); returns the reference's.
    ``turns``: a measured rotation's history (:func:`_angle_history`), or None: the latest
    rotational speed ``rot`` (px/s) times the time."""
    from evchain.kernels.ttc import baseline_tau
    from tests.naive.ttc import angle_naive, rotational_speed_naive

    px, py, nx, ny, d0, ti = args[:6]
    kargs = (px, py, nx, ny, d0, rot, *args[5:])
    if turns is None:
        want = baseline_tau_naive(S[pol], *args, lambda tq: rot * (ti - tq) * 1e-6)
        got = baseline_tau(S, pol, *kargs, False, np.zeros(1), np.zeros((1, 3)), 0, 0.0, 0.0,
                           0.0, 0.0, 0.0, 0.0)
    else:
        times, angles, w = turns
        history = list(zip(times, angles, strict=True))

        def shift_of(tq):
            turned = angle_naive(history, ti, w) - angle_naive(history, tq, w)
            return rotational_speed_naive(px, py, nx, ny, turned, f, cx, cy)

        want = baseline_tau_naive(S[pol], *args, shift_of)
        padded_t = np.concatenate([times, np.full(3, np.nan)])
        padded = np.concatenate([angles, np.full((3, 3), np.nan)])
        got = baseline_tau(S, pol, *kargs, True, padded_t, padded, len(times), *w, f, cx, cy)
    assert np.isfinite(got)
    # tau = d dt / (dd - shift): where the edge barely moved (tau of hours) the difference
    # loses digits in proportion to tau over the baseline, the same in either order of rounding
    assert got == pytest.approx(want, rel=1e-12 * max(1.0, abs(want)), abs=1e-15)
    return want


def test_angle_history_matches_reference():
    """The rotation history kept by ``record_angle`` gives the reference's angles (over all
    entries) at every time from its oldest kept entry on, and keeps every time within the
    longest baseline of the newest entry while it has room for them (else it drops the older
    half); hard cases: one entry, times before the oldest, at an entry, after the newest, zero
    angular velocities, a history of two entries."""
    from evchain.kernels.ttc import CARRY, angle_at, record_angle
    from tests.naive.ttc import angle_naive

    rng = np.random.default_rng(11)
    for case in range(24):
        # entries 1-7 ms apart and keep <= 9 ms: 12 entries always hold the last 9 ms
        cap = 12 if case % 3 else int(rng.integers(2, 6))
        keep = float(rng.integers(1, 10)) * 1000.0
        angle_t, angle = np.zeros(cap), np.zeros((cap, 3))
        carry = np.zeros(1, CARRY)
        history, t = [], 0.0
        for _ in range(int(rng.integers(1, 60))):
            t += float(rng.integers(1, 8)) * 1000.0
            w = np.zeros(3) if case % 4 == 0 else rng.normal(0, 0.5, 3)
            record_angle(angle_t, angle, carry[0], t, *w, keep)
            history.append((t, angle_naive(history, t, w)))
            n = int(carry[0]["n_angles"])
            assert 1 <= n <= cap and angle_t[n - 1] == t
            if cap == 12:
                assert angle_t[0] <= max(t - keep, history[0][0])
            for tq in [t, t - keep, t + 2500.0, *rng.uniform(t - keep, t, 5), *angle_t[:n]]:
                if tq >= angle_t[0]:
                    got = angle_at(angle_t, angle, n, tq, *w)
                    want = angle_naive(history, tq, w)
                    assert np.allclose(got, want, rtol=1e-12, atol=1e-15)


def test_baseline_tau_matches_reference_on_ties_and_borders():
    """Hard inputs of the walk beside the edge: many equal times (the first newest is taken),
    positions off the pixel grid and on the image's border, steps leaving the image."""

    rng = np.random.default_rng(7)
    S = np.full((2, 12, 16), -1e300)
    S[0] = rng.integers(0, 6, (12, 16)) * 100_000.0
    S[1] = np.where(rng.random((12, 16)) < 0.5, -1e300, 300_000.0)
    got_any = 0
    for i in range(3000):
        pol = i % 2
        px = float(rng.choice([0, 15, rng.uniform(-0.4, 15.4), rng.integers(0, 16)]))
        py = float(rng.choice([0, 11, rng.uniform(-0.4, 11.4), rng.integers(0, 12)]))
        ang = rng.uniform(0, 2 * np.pi) if i % 2 else rng.integers(0, 8) * np.pi / 4
        args = (px, py, np.cos(ang), np.sin(ang), float(rng.uniform(-3, 20)), 600_000.0,
                int(rng.integers(1, 8)), 1e6, int(rng.integers(0, 5)))
        turns = _angle_history(rng, 0, 700_000, 6) if i % 3 == 0 else None
        rot = float(rng.normal(0, 5)) if i % 3 == 1 else 0.0
        got_any += _baseline_agrees(S, pol, args, turns, rot, 10.0, 8.0, 6.0) > 0
    assert got_any > 100


def test_baseline_contract():
    # the pixels' last times carry over packet cuts: the output must not depend on them
    ref = check_filter(Ttc, {**PX, "baseline_px": 6, "min_samples": 4},
                       with_true_foe(edge_approach(duration_s=1.0, jitter_us=2_000.0)))
    assert len(ref["series:ttc"]) > 5


# -- credible clusters only ----------------------------------------------------------------


def run_ttc_metrics(packets, **params):
    params.setdefault("baseline_px", 0)
    params = {**PX, **params}
    ctx = Context()
    f = Ttc()
    f.setup(Ttc.Params(**params), ctx)
    out = FlowPacket.concat([f.process(p) for p in packets])
    f.flush()
    return out, ctx.metrics["ttc_filter"]


def disagreeing(duration_us=1_000_000, n=40_000, seed=0):
    """Radial flow below the FOE whose speeds vary a thousandfold at random: every event's tau
    is (p - foe).v / |v|^2, so the samples of any cluster spread over three decades (a relative
    spread far above 1, as with rotational flow read as expansion): no single surface
    approaching."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(FOE[0] - 40, FOE[0] + 40, n)
    y = rng.uniform(FOE[1] + 10, G.height - 1, n)
    r = np.hypot(x - FOE[0], y - FOE[1])
    s = np.exp(rng.uniform(np.log(3.0), np.log(3000.0), n))
    t = np.sort(rng.integers(0, duration_us, n))
    p = FlowPacket(geometry=G, t_start=0, t_end=duration_us, x=np.round(x).astype(np.uint16),
                   y=np.round(y).astype(np.uint16), t=t, p=np.ones(n, np.int8),
                   vx=((x - FOE[0]) / r * s).astype(np.float32),
                   vy=((y - FOE[1]) / r * s).astype(np.float32))
    from evchain.testing.contract import slice_packet

    return with_true_foe([slice_packet(p, a, a + 100_000) for a in range(0, duration_us,
                                                                           100_000)])


def test_no_ttc_from_clusters_whose_samples_disagree():
    packets = disagreeing()
    out, m = run_ttc_metrics(packets)
    assert len(out.series["ttc_clusters"]) > 100      # the clusters are there, with a tau
    assert len(out.series["ttc"]) == 0
    assert m["ticks"] == 100 and m["estimates"] == 0
    assert m["no_estimate"]["no credible cluster"] >= 95
    # without the test every tick reports one of them
    old, _ = run_ttc_metrics(packets, max_rel_spread=None)
    assert len(old.series["ttc"]) >= 95


def test_consistent_clusters_stay_credible():
    """Noisy normal flow of one approaching surface: its samples agree, every tick after
    the first samples has a TTC."""
    out, m = run_ttc_metrics(with_true_foe(approach(**NOISY)))
    assert m["estimates"] >= m["ticks"] - 5
    assert m["no_estimate"]["no credible cluster"] == 0


def test_no_ttc_below_the_smallest_event_tau():
    """An obstacle 0.3 s away whose events stop after 0.25 s: its cluster lives on (long
    activity memory) with a tau predicted to fall 1 s/s; below min_tau_s (0.02 s) it is no
    longer reported, though the cluster still is."""
    packets = with_true_foe(approach(tau0=0.3, duration_us=250_000, n=40_000))
    quiet = [FlowPacket.empty(G, t, t + 10_000) for t in range(250_000, 400_000, 10_000)]
    out, m = run_ttc_metrics(packets + with_true_foe(quiet), activity_tau_ms=2000.0)
    s, cl = out.series["ttc"], out.series["ttc_clusters"]
    assert len(s) > 10 and s["tau_s"].min() >= 0.02
    assert (cl["tau_s"] < 0.02).any()                 # predicted below, not reported
    assert m["no_estimate"]["no credible cluster"] >= 1


def test_no_ttc_predicted_past_its_data():
    """An obstacle at 3 s whose events stop at 0.5 s: its cluster lives on (long activity
    memory) with a tau predicted to fall 1 s/s, reported only while its newest sample is no
    older than that tau (until about 1.75 s, where 3 - t = t - 0.5); the cluster itself is
    still listed after."""
    packets = with_true_foe(approach(duration_us=500_000, n=40_000))
    quiet = [FlowPacket.empty(G, t, t + 100_000) for t in range(500_000, 2_200_000, 100_000)]
    out, m = run_ttc_metrics(packets + with_true_foe(quiet), activity_tau_ms=5000.0)
    s, cl = out.series["ttc"], out.series["ttc_clusters"]
    newest = packets[-1].t[-1] * 1e-6
    assert s["t"].max() * 1e-6 >= 1.7
    last = s[s["t"] >= 1_000_000]
    assert (last["t"] * 1e-6 - newest <= last["tau_s"] + 1e-9).all()
    assert (cl["t"] > 1_800_000).any()                 # the cluster is still there
    assert m["no_estimate"]["no credible cluster"] >= 30


# -- px and px/s that follow the camera ---------------------------------------------------


@pytest.mark.parametrize("scale", [1.0, 2.0, 0.75])
def test_px_parameters_follow_the_focal_length(scale):
    """Left null, region B, the distance from the FOE, the speed bounds and the clusters'
    sizes are their reference camera values (60, 5, 2, 20000, 6, 15, 4) times f / 380.6 px:
    twice that on 640x480 with the same field of view; the baseline's px of the grid stay."""
    from evchain.core.camera_scale import REFERENCE_FOCAL_PX

    f = Ttc()
    f.setup(Ttc.Params(), Context())
    k = f._constants(Geometry(int(320 * scale), int(240 * scale), f=scale * REFERENCE_FOCAL_PX))
    got = (k.half_width, k.min_dist, k.min_speed, k.max_speed, k.init_size, k.max_size,
           k.join_margin)
    np.testing.assert_allclose(got, np.array([60.0, 5.0, 2.0, 20_000.0, 6.0, 15.0, 4.0]) * scale,
                               rtol=1e-12)
    assert (k.base_px, k.min_below) == (6, 0.0)


def test_px_parameters_given_are_kept():
    f = Ttc()
    f.setup(Ttc.Params(**PX), Context())
    k = f._constants(Geometry(640, 480, f=761.2))
    assert (k.half_width, k.min_dist, k.min_speed, k.max_speed, k.init_size, k.max_size,
            k.join_margin) == tuple(PX.values())
