"""frame_flow on synthetic frames: a textured plane translating, and one approaching the camera
(expansion about a known FOE) through the FOE and TTC stages."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.packets import FlowPacket, FramePacket, Geometry
from evchain.filters.foe_lines import FoeLines
from evchain.filters.foe_map import FoeMap
from evchain.filters.frame_flow import FrameFlow
from evchain.filters.ttc import Ttc
from evchain.testing.contract import check_filter, make_context, recut, run_filter
from evchain.testing.synthetic import ExpansionTruth
from tests.naive.ttc import PX

cv2 = pytest.importorskip("cv2")

G = Geometry(128, 96, f=100.0)
FPS_US = 33_333


def texture(u, v):
    """A smooth random-looking texture in [0.1, 0.9] (intensity of a plane's point (u, v))."""
    k = [(0.21, 0.13, 0.3), (-0.11, 0.27, 1.1), (0.35, -0.06, 2.0), (0.07, 0.41, 0.7),
         (-0.29, -0.19, 1.6)]
    s = sum(np.sin(a * u + b * v + c) for a, b, c in k)
    return 0.5 + 0.08 * s


def stream(image_at, n: int, dt_us: int = FPS_US, geometry: Geometry = G) -> FramePacket:
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width].astype(np.float64)
    t = dt_us * np.arange(n, dtype=np.int64)
    frames = np.stack([image_at(xs, ys, float(ti) * 1e-6) for ti in t]).astype(np.float32)
    q = np.floor(frames * 255 + 0.5) / 255          # ideal 8-bit frames
    return FramePacket(geometry=geometry, t_start=0, t_end=int(t[-1]) + 1,
                       frames=q.astype(np.float32), t=t)


def run(cls, params, packets, truth=None):
    f = cls()
    f.id = cls.name
    f.setup(cls.Params(**params), make_context(packets[0].geometry, truth))
    return run_filter(f, packets)


@pytest.mark.parametrize("method", ["dis", "farneback"])
def test_translation_speed_and_direction(method):
    v = (45.0, -30.0)   # px/s: 1.5 and 1 px per frame at 30 fps
    pk = stream(lambda xs, ys, t: texture(xs - v[0] * t, ys - v[1] * t), 8)
    out = FlowPacket.concat(run(FrameFlow, {"method": method}, recut([pk], [100_000])))
    assert len(out) == 7 * len(np.arange(4, 92, 4)) * len(np.arange(4, 124, 4))
    assert set(np.unique(out.t)) == set(pk.t[1:].tolist())
    err = np.hypot(out.vx - v[0], out.vy - v[1])
    # median within 2 % of the speed (54 px/s), 90 % of the vectors within 10 %
    assert np.median(err) < 0.02 * np.hypot(*v)
    assert np.quantile(err, 0.9) < 0.10 * np.hypot(*v)


def expansion(foe, tau0_s):
    """A fronto-parallel textured plane approached at constant speed: contact at tau0_s; the
    image of a plane point scales by tau0 / (tau0 - t) about the FOE."""
    def image_at(xs, ys, t):
        s = (tau0_s - t) / tau0_s
        return texture((xs - foe[0]) * s, (ys - foe[1]) * s)
    return image_at


def test_expansion_flow_foe_and_ttc():
    foe, tau0 = (70.0, 40.0), 2.0
    truth = ExpansionTruth(foe, tau0)
    pk = stream(expansion(foe, tau0), 31)                 # 1 s: tau from 2 s to 1 s
    flow = run(FrameFlow, {"method": "dis"}, recut([pk], [300_000, 600_000]))
    whole = FlowPacket.concat(flow)
    t = whole.t.astype(np.float64)
    # the flow between frames k-1 and k at frame k's pixels is (p - foe) / tau(t_{k-1}):
    # the true flow at the earlier frame, one frame interval late
    tau_prev = tau0 - (t - FPS_US) * 1e-6
    ux, uy = (whole.x - foe[0]) / tau_prev, (whole.y - foe[1]) / tau_prev
    far = np.hypot(whole.x - foe[0], whole.y - foe[1]) > 15
    err = np.hypot(whole.vx - ux, whole.vy - uy)[far] / np.hypot(ux, uy)[far]
    gain = (whole.vx * ux + whole.vy * uy)[far] / (ux * ux + uy * uy)[far]
    assert np.median(err) < 0.08                  # DIS's patches translate; the image scales
    assert abs(np.median(gain) - 1) < 0.02        # but the speeds are unbiased
    # FOE by half-plane voting on the full flow (whole sensor)
    votes = run(FoeMap, {"region_radius_px": 0, "tau_ms": 100,
                         "estimate_every_us": 10_000}, flow)
    est = np.concatenate([p.series["foe"] for p in votes])
    late = est[est["t"] > 300_000]
    assert np.median(np.abs(late["x"] - foe[0])) < 1.0
    assert np.median(np.abs(late["y"] - foe[1])) < 1.0
    # FOE where the full flow's lines meet
    lines = run(FoeLines, {}, flow)
    est = np.concatenate([p.series["foe"] for p in lines])
    assert len(est) > 90 and np.all(est["t"] >= FPS_US)
    assert np.median(np.abs(est["x"] - foe[0])) < 0.6
    assert np.median(np.abs(est["y"] - foe[1])) < 0.6
    # TTC on the full flow: per-event tau from the flow (baseline_px 0), clustered
    ttc = run(Ttc, {**PX, "baseline_px": 0, "region_b_half_width_px": 40}, votes, truth)
    tau = np.concatenate([p.series["ttc"] for p in ttc])
    tau = tau[tau["t"] > 500_000]
    assert len(tau) > 40
    rel = np.abs(tau["tau_s"] - truth.ttc(tau["t"])) / truth.ttc(tau["t"])
    assert np.median(rel) < 0.05


def test_gradient_mask_and_contract():
    pk = stream(lambda xs, ys, t: np.where(xs < 64, 0.5, texture(xs - 40 * t, ys)), 5)
    packets = recut([pk], [40_000, 40_001, 100_000])
    every = check_filter(FrameFlow, {}, packets)
    masked = check_filter(FrameFlow, {"min_gradient": 0.01}, packets)
    assert 0 < len(masked["x"]) < len(every["x"])
    assert np.all(masked["x"] >= 63)        # the flat left half has no gradient
    check_filter(FrameFlow, {"method": "farneback", "grid_px": 8}, packets)


def test_foe_lines_contract():
    foe, tau0 = (70.0, 40.0), 2.0
    flow = run(FrameFlow, {}, [stream(expansion(foe, tau0), 8)])
    out = check_filter(FoeLines, {"window_ms": 50}, recut(flow, [70_000, 70_001, 150_000]))
    assert len(out["series:foe"]) > 10


def test_baseline_measures_over_several_frames():
    v = (12.0, 3.0)   # slow: 0.4 px per frame at 30 fps, 1.2 px over 100 ms
    pk = stream(lambda xs, ys, t: texture(xs - v[0] * t, ys - v[1] * t), 9)
    out = FlowPacket.concat(run(FrameFlow, {"baseline_ms": 99}, recut([pk], [50_000])))
    assert set(np.unique(out.t)) == set(pk.t[3:].tolist())   # from frame 3 (99.999 ms) on
    err = np.hypot(out.vx - v[0], out.vy - v[1])
    assert np.median(err) < 0.02 * np.hypot(*v)
    check_filter(FrameFlow, {"baseline_ms": 60}, recut([pk], [120_000, 120_001]))
