"""foe_map recovers known FOEs on synthetic expansion flow; hard inputs; filter contract."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.filters.foe_map import FoeMap
from evchain.testing.contract import check_filter
from tests.naive.foe_map import expansion_packets

G = Geometry(128, 96, f=100.0)
#: the settings these tests were written for (the defaults derive the radius and s0 from G's
#: focal length, and read every 10 ms)
BASE = {"tau_ms": 300.0, "region_radius_px": 60.0, "estimate_every_us": 1000,
        "speed_weight_pxs": 5.0}


def run(packets, **params):
    f = FoeMap()
    f.setup(FoeMap.Params(**{**BASE, **params}), Context())
    return FlowPacket.concat([f.process(p) for p in packets])


def last_error(out, foe):
    s = out.series["foe"]
    assert len(s) > 0
    assert np.isfinite(s["x"]).all() and np.isfinite(s["y"]).all()
    return abs(s["x"][-1] - foe[0]), abs(s["y"][-1] - foe[1])


# (generator options, FOE, region radius, tolerance in px)  -- stated tolerances
RECOVERY = {
    "full flow": (dict(), (60.0, 45.0), 60.0, 0.5),
    "normal flow": (dict(normal_only=True), (70.3, 40.6), 60.0, 0.7),
    "noise 20% + 10% outliers": (dict(normal_only=True, noise_frac=0.2, outlier_frac=0.1),
                                 (58.0, 50.0), 60.0, 1.5),
    "near the border": (dict(normal_only=True), (4.0, 91.0), 0.0, 1.5),
}


@pytest.mark.parametrize("name", list(RECOVERY))
def test_recovers_foe(name):
    opts, foe, radius, tol = RECOVERY[name]
    packets = expansion_packets(foe=foe, n=30_000, geometry=G, duration_us=300_000, **opts)
    out = run(packets, region_radius_px=radius, estimate_every_us=5000)
    dx, dy = last_error(out, foe)
    assert dx <= tol and dy <= tol, (name, dx, dy)
    assert len(out) == sum(len(p) for p in packets)  # flow passes through unchanged
    np.testing.assert_array_equal(out.vx, np.concatenate([p.vx for p in packets]))


def test_foe_outside_region_a_lands_on_its_border():
    foe = (10.0, 85.0)
    packets = expansion_packets(foe=foe, n=30_000, geometry=G, duration_us=300_000,
                                normal_only=True)
    out = run(packets, region_radius_px=30.0, estimate_every_us=5000)
    s = out.series["foe"][-1]
    c = np.array([G.cx, G.cy])
    r = np.hypot(s["x"] - c[0], s["y"] - c[1])
    assert 27.0 <= r <= 30.5
    want = math.atan2(foe[1] - c[1], foe[0] - c[0])
    got = math.atan2(s["y"] - c[1], s["x"] - c[0])
    assert abs(math.degrees(got - want)) < 6.0


def test_follows_a_moving_foe_with_decay():
    a = expansion_packets(foe=(50.0, 40.0), n=20_000, geometry=G, duration_us=200_000, seed=1,
                          normal_only=True)
    b = expansion_packets(foe=(75.0, 55.0), n=20_000, geometry=G, duration_us=200_000, seed=2,
                          normal_only=True)
    b = [p.replace(t=p.t + 200_000, t_start=p.t_start + 200_000, t_end=p.t_end + 200_000)
         for p in b]
    out = run(a + b, tau_ms=20.0, estimate_every_us=5000)
    s = out.series["foe"]
    mid = s[s["t"] == 200_000][0]
    assert abs(mid["x"] - 50) < 1 and abs(mid["y"] - 40) < 1
    assert abs(s["x"][-1] - 75) < 1 and abs(s["y"][-1] - 55) < 1


def hard_packet(vx, vy, x=None, y=None, n=200):
    rng = np.random.default_rng(3)
    x = rng.integers(0, G.width, n) if x is None else np.full(n, x)
    y = rng.integers(0, G.height, n) if y is None else np.full(n, y)
    return FlowPacket(geometry=G, t_start=0, t_end=20_000, x=x.astype(np.uint16),
                      y=y.astype(np.uint16), t=np.sort(rng.integers(0, 20_000, n)),
                      p=np.ones(n, np.int8), vx=np.full(n, vx, np.float32),
                      vy=np.full(n, vy, np.float32))


def test_zero_flow_gives_no_estimate():
    out = run([hard_packet(0.0, 0.0)], estimate_every_us=1000)
    assert len(out.series["foe"]) == 0


@pytest.mark.parametrize("v", [(50.0, 0.0), (0.0, -50.0), (1e-30, 0.0)])
def test_flow_along_an_axis_is_finite(v):
    out = run([hard_packet(*v)], estimate_every_us=1000, region_radius_px=0)
    s = out.series["foe"]
    assert len(s) > 0 and np.isfinite(s["x"]).all() and np.isfinite(s["y"]).all()
    assert np.all(s["support"] > 0)


def test_event_exactly_at_the_foe():
    foe = (64.0, 48.0)
    packets = expansion_packets(foe=foe, n=5000, geometry=G, duration_us=100_000, n_packets=1)
    p = packets[0]
    at = hard_packet(1.0, 1.0, x=64, y=48, n=5)   # p == foe: (p - q).v = 0 at q = p
    merged = FlowPacket.concat([p, at.replace(t_start=100_000, t_end=120_000,
                                              t=at.t + 100_000)])
    out = run([merged], estimate_every_us=2000)
    dx, dy = last_error(out, foe)  # finite; those votes cut the plateau around the FOE in half
    assert dx < 3 and dy < 3


def test_min_speed_and_min_support():
    p = hard_packet(3.0, 4.0)
    assert len(run([p], min_speed_pxs=6.0).series["foe"]) == 0
    assert len(run([p], min_speed_pxs=4.0).series["foe"]) > 0
    assert len(run([p], min_support=1e9).series["foe"]) == 0


def test_contract():
    packets = expansion_packets(foe=(60.0, 45.0), n=3000, geometry=G, duration_us=100_000,
                                normal_only=True, noise_frac=0.1, n_packets=3)
    ref = check_filter(FoeMap, {"estimate_every_us": 3000, "max_angle_deg": 80.0}, packets)
    assert len(ref["series:foe"]) > 20


# -- the noise test: no estimate from flow whose directions carry no FOE -----------------------


def noise_packets(n=20_000, duration_us=500_000, n_packets=5, seed=0, cut=None):
    """Flow events at random pixels and times with random directions and speeds (2-200 px/s):
    no FOE anywhere."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, duration_us, n))
    ang = rng.uniform(0, 2 * np.pi, n)
    s = rng.uniform(2.0, 200.0, n)
    p = FlowPacket(geometry=G, t_start=0, t_end=duration_us,
                   x=rng.integers(0, G.width, n).astype(np.uint16),
                   y=rng.integers(0, G.height, n).astype(np.uint16), t=t,
                   p=np.ones(n, np.int8), vx=(s * np.cos(ang)).astype(np.float32),
                   vy=(s * np.sin(ang)).astype(np.float32))
    cuts = np.linspace(0, duration_us, n_packets + 1).astype(int) if cut is None else cut
    from evchain.testing.contract import slice_packet

    return [slice_packet(p, int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]


@pytest.mark.parametrize("radius", [60.0, 0.0])
def test_no_estimate_from_flow_without_an_foe(radius):
    """Random directions: without the test an estimate at every read (as before it existed),
    with it none, and the metrics say why."""
    packets = noise_packets()
    # reads every ms; the one at 0 has no votes yet
    assert len(run(packets, significance=None, region_radius_px=radius).series["foe"]) == 499
    f = FoeMap()
    ctx = Context()
    f.setup(FoeMap.Params(**{**BASE, "region_radius_px": radius}), ctx)
    out = FlowPacket.concat([f.process(p) for p in packets])
    f.flush()
    assert len(out.series["foe"]) == 0
    m = ctx.metrics["foe_map"]
    assert m["reads"] == 500 and m["estimates"] == 0
    assert m["no_estimate"] == {"no votes yet": 1, "consensus at noise level": 499}


def test_expansion_in_noise_is_found():
    """Expansion flow under three times as many noise votes still has its FOE (the consensus
    at the FOE is about 1/4 + 3/4 * 1/2), from the first reads on."""
    foe = (60.0, 45.0)
    flow = expansion_packets(foe=foe, n=5000, geometry=G, duration_us=500_000, n_packets=5,
                             normal_only=True)
    noise = noise_packets(n=15_000)
    both = [FlowPacket.concat([a, b]) for a, b in zip(flow, noise, strict=True)]
    both = [p.replace(**{c: getattr(p, c)[np.argsort(p.t, kind="stable")]
                         for c in ("x", "y", "t", "p", "vx", "vy")}) for p in both]
    s = run(both).series["foe"]
    assert len(s) >= 490
    assert abs(s["x"][-1] - foe[0]) < 3 and abs(s["y"][-1] - foe[1]) < 3


def test_noise_test_matches_a_plain_computation():
    """The estimates kept are exactly those whose consensus exceeds the bound computed from
    all votes before the read (weights exp(-(T - t) / tau) s0 / (s0 + |v|)), for any cuts;
    the kernel's total is that sum of weights, and the metrics count the others (the kernel
    counts them across packets)."""
    foe = (60.0, 45.0)
    flow = expansion_packets(foe=foe, n=600, geometry=G, duration_us=500_000, n_packets=1,
                             normal_only=True)[0]
    noise = noise_packets(n=3000, n_packets=1)[0]
    allp = FlowPacket.concat([flow, noise])
    order = np.argsort(allp.t, kind="stable")
    allp = allp.replace(**{c: getattr(allp, c)[order] for c in ("x", "y", "t", "p", "vx", "vy")})
    params = dict(tau_ms=50.0, estimate_every_us=5000)
    every = run([allp], significance=None, **params).series["foe"]
    s = np.hypot(allp.vx.astype(np.float64), allp.vy.astype(np.float64))
    w0 = 5.0 / (5.0 + s)
    cells = sum(1 for yy in range(G.height) for xx in range(G.width)
                if (xx - G.cx) ** 2 + (yy - G.cy) ** 2 <= 60.0 ** 2)
    want = []
    for e in every:
        before = allp.t < e["t"]
        w = w0[before] * np.exp(-(e["t"] - allp.t[before]) / 50_000.0)
        assert e["total"] == pytest.approx(w.sum(), rel=1e-9)
        n_eff = w.sum() ** 2 / (w ** 2).sum()
        if e["support"] / e["total"] > 0.5 + math.sqrt(math.log(cells / 1e-3) / (2 * n_eff)):
            want.append(e["t"])
    assert 0 < len(want) < len(every)     # the test decides both ways on this stream
    for cut in ([0, 500_000], [0, 1234, 250_000, 250_001, 500_000], list(range(0, 500_001,
                                                                          7000)) + [500_000]):
        from evchain.testing.contract import slice_packet

        packets = [slice_packet(allp, a, b) for a, b in zip(cut[:-1], cut[1:], strict=True)
                   if b > a]
        f = FoeMap()
        ctx = Context()
        f.setup(FoeMap.Params(**{**BASE, **params}), ctx)
        got = FlowPacket.concat([f.process(p) for p in packets]).series["foe"]["t"]
        np.testing.assert_array_equal(got, want)
        f.flush()
        reads = 100  # T = 0, 5000, ..., 495000
        assert ctx.metrics["foe_map"] == {
            "reads": reads, "estimates": len(want),
            "no_estimate": {"no votes yet": reads - len(every),
                            "consensus at noise level": len(every) - len(want)}}


@pytest.mark.parametrize("scale", [1.0, 2.0, 0.75])
def test_px_parameters_follow_the_focal_length(scale):
    """region_radius_px and speed_weight_pxs left null are 60 px and 5 px/s on the reference
    camera (320x240, 35 deg) times f / 380.6 px: twice that on 640x480 with the same field of
    view."""
    from evchain.core.camera_scale import REFERENCE_FOCAL_PX

    f = FoeMap()
    f.setup(FoeMap.Params(), Context())
    f._allocate(Geometry(int(320 * scale), int(240 * scale), f=scale * REFERENCE_FOCAL_PX))
    assert f._prm["radius"][0] == pytest.approx(60.0 * scale, rel=1e-12)
    assert f._prm["speed_w0"][0] == pytest.approx(5.0 * scale, rel=1e-12)


def test_px_parameters_given_are_kept():
    """Values given are taken as they are on any camera; 0 is the whole sensor and unweighted
    votes."""
    from evchain.core.camera_scale import REFERENCE_FOCAL_PX

    g = Geometry(640, 480, f=2 * REFERENCE_FOCAL_PX)
    f = FoeMap()
    f.setup(FoeMap.Params(region_radius_px=45.0, speed_weight_pxs=7.0), Context())
    f._allocate(g)
    assert (f._prm["radius"][0], f._prm["speed_w0"][0]) == (45.0, 7.0)
    f.setup(FoeMap.Params(region_radius_px=0, speed_weight_pxs=0), Context())
    f._allocate(g)
    assert f._prm["speed_w0"][0] == 0.0
    assert f._prm["radius"][0] == pytest.approx(0.5 * np.hypot(640, 480))  # the whole sensor
    assert f.map_now(0).shape == (480, 640) and not np.isnan(f.map_now(0)).any()
