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


def run(packets, **params):
    f = FoeMap()
    f.setup(FoeMap.Params(**params), Context())
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
    "near the border": (dict(normal_only=True), (4.0, 91.0), None, 1.5),
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
    out = run([hard_packet(*v)], estimate_every_us=1000, region_radius_px=None)
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
