"""Filter lk_flow: calibrated speeds on synthetic edges, jAER's behaviour, contract, DVSFLOW16."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from evchain.core.camera_scale import REFERENCE_FOCAL_PX
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, FlowPacket, Geometry
from evchain.filters.lk_flow import GRADIENTS, LKFlow
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import moving_edge_events, random_events

DVSFLOW16 = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dvsflow16"
GEOM = Geometry(32, 24, f=REFERENCE_FOCAL_PX)


#: the fixed window these tests were written for (the default adapts it to slow edges)
FIXED = {"max_window_us": 0}


def run(events: EventPacket, **params) -> FlowPacket:
    f = LKFlow()
    f.setup(LKFlow.Params(**{**FIXED, **params}), Context(geometry=events.geometry))
    out = f.process(events)
    out.validate("lk_flow output")
    return out


run_fixed = run


def edge_from_centre(speed, angle_deg, geometry=GEOM, travel_px=10.0):
    """An edge that starts through the image centre and travels ``travel_px``."""
    a = np.radians(angle_deg)
    vx, vy = speed * np.cos(a), speed * np.sin(a)
    extent = 0.5 * np.hypot(geometry.width, geometry.height)
    duration = int(np.ceil(travel_px / speed * 1e6))
    return moving_edge_events(vx, vy, geometry, duration_us=duration, offset_px=-extent), vx, vy


SPEEDS = [1.0, 10.0, 100.0, 1000.0, 5000.0]
ANGLES = [0, 45, 90, 135, 180, 225, 270, 315]


@pytest.mark.parametrize("gradient", list(GRADIENTS))
def test_calibrated_normal_flow_8_directions_1_to_5000_pxs(gradient):
    """Stated tolerance: per event, speed within 2 % and direction within 2 degrees, for at
    least 95 % of the flow events; median speed within 0.5 %. The window must hold the edge's
    passage over the stencil: window_us = max(80 ms, 8 px / speed)."""
    for speed in SPEEDS:
        window = max(80_000, int(8 / speed * 1e6))
        for angle in ANGLES:
            ev, vx, vy = edge_from_centre(speed, angle)
            out = run(ev, gradient=gradient, window_us=window)
            where = f"{gradient} {speed} px/s {angle} deg"
            assert len(out) >= 0.2 * len(ev), f"{where}: only {len(out)} of {len(ev)}"
            s = np.hypot(out.vx, out.vy)
            rel = np.abs(s / speed - 1)
            ang = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(out.vy, out.vx)
                                                          - np.arctan2(vy, vx))))))
            assert np.median(rel) < 0.005, f"{where}: median speed {np.median(s)}"
            assert np.mean(rel < 0.02) >= 0.95, f"{where}: speeds {np.percentile(s, [5, 95])}"
            assert np.mean(ang < 2.0) >= 0.95, f"{where}: angles up to {ang.max()}"


def test_faithful_savitzky_golay_gives_jaer_33_pxs_whatever_the_speed():
    """jAER's LK with the Savitzky-Golay gradient takes the normal-flow branch and returns
    about 33 px/s (r = 2, 80 ms window) whatever the true speed."""
    g = Geometry(64, 48, f=REFERENCE_FOCAL_PX)
    for speed in [100.0, 400.0, 1500.0]:
        ev = moving_edge_events(speed, 0.0, g, duration_us=int(60 / speed * 1e6))
        out = run(ev, gradient="savitzky_golay", mode="faithful", speed_control=False)
        s = np.hypot(out.vx, out.vy)
        assert len(out) > 100
        assert abs(np.median(s) - 33.3) < 1.5, (speed, np.median(s))


def test_faithful_speed_control_starts_from_zero_mean():
    """jAER's running mean starts at 0, so the first flow events are rejected as speeders;
    calibrated mode starts the mean at the first speed."""
    ev = moving_edge_events(200.0, 0.0, Geometry(64, 48, f=REFERENCE_FOCAL_PX), duration_us=300_000)
    on = run(ev, gradient="central", mode="faithful")
    off = run(ev, gradient="central", mode="faithful", speed_control=False)
    assert len(on) < len(off)
    assert on.t[0] > off.t[0]
    cal_on = run(ev, gradient="central")
    cal_off = run(ev, gradient="central", speed_control=False)
    assert len(cal_on) == len(cal_off)


def test_refractory_suppresses_flow_but_updates_memory():
    g = Geometry(32, 24, f=REFERENCE_FOCAL_PX)
    ev = moving_edge_events(300.0, 0.0, g, duration_us=100_000)
    twice = EventPacket.concat([ev, ev.replace(t=ev.t + 100_000, t_start=100_000,
                                               t_end=200_000)])
    out = run(twice, gradient="central", refractory_us=150_000)
    # the second sweep fires each pixel 100 ms after the first: no flow for it
    assert len(out) and out.t.max() < 100_000
    out0 = run(twice, gradient="central", refractory_us=0)
    assert out0.t.max() >= 100_000


def event_stream():
    g = Geometry(48, 36, f=REFERENCE_FOCAL_PX)
    edge = moving_edge_events(400.0, 150.0, g, duration_us=150_000)
    noise = random_events(300, g, 0, 150_000, seed=3)
    merged = EventPacket.concat([edge, noise])
    merged = merged.select(np.argsort(merged.t, kind="stable"))
    return recut([merged], [40_000, 90_000])


@pytest.mark.parametrize("mode,gradient", [("calibrated", "savitzky_golay"),
                                           ("calibrated", "central2"),
                                           ("calibrated", "backward"),
                                           ("faithful", "central")])
def test_contract(mode, gradient, tmp_path):
    check_filter(LKFlow, {"mode": mode, "gradient": gradient, "refractory_us": 5_000},
                 event_stream(), out_dir=tmp_path)


def test_packet_cuts_do_not_change_flow():
    packets = event_stream()
    whole = run(EventPacket.concat(packets), gradient="central")
    f = LKFlow()
    f.setup(LKFlow.Params(**FIXED, gradient="central"), Context(geometry=packets[0].geometry))
    parts = [f.process(p) for p in recut(packets, [1_000, 1_001, 77_777])]
    cut = FlowPacket.concat(parts)
    assert len(whole) > 50
    np.testing.assert_array_equal(cut.t, whole.t)
    np.testing.assert_array_equal(cut.vx, whole.vx)
    f.reset()
    again = FlowPacket.concat([f.process(p) for p in packets])
    np.testing.assert_array_equal(again.vy, whole.vy)


def _square():
    aedat = pytest.importorskip("evchain.io.aedat2")
    path = DVSFLOW16 / "TranslatingSquare.aedat"
    gt = DVSFLOW16 / "gtTranslatingSquare.mat"
    if not (path.exists() and gt.exists()):
        pytest.skip("DVSFLOW16 data not found in ../shared/data/dvsflow16")
    from scipy.io import loadmat
    return aedat.read_aedat2(path, chip="davis240"), loadmat(gt)


def square_aee(out, gt):
    """AEE against gtTranslatingSquare.mat (rows: jAER's bottom-up y; vy up = positive)."""
    t0, t1 = gt["ts"].ravel()
    m = (out.t >= t0) & (out.t < t1)
    x, y = out.x[m].astype(int), out.y[m].astype(int)
    gvx = gt["vxGT"].astype(float)[179 - y, x]
    gvy = -gt["vyGT"].astype(float)[179 - y, x]
    ok = (gvx != 0) | (gvy != 0)
    return float(np.mean(np.hypot(out.vx[m][ok] - gvx[ok], out.vy[m][ok] - gvy[ok]))), ok.sum()


def test_dvsflow16_square_calibrated_and_faithful():
    ev, gt = _square()
    # the recording has no focal length: the windows of the reference camera, as in
    # pipelines/dvsflow16-square-lk.yaml
    run = functools.partial(run_fixed, window_us=80_000, refractory_us=150_000)
    for gradient in GRADIENTS:
        out = run(ev, gradient=gradient)
        aee, n = square_aee(out, gt)
        assert n > 100 and aee < 2.0, (gradient, aee, n)  # truth: 20 px/s
        assert np.median(np.hypot(out.vx, out.vy)) == pytest.approx(20.0, rel=0.02)
    # jAER's SG: one plane over two fired columns, lambda1 = 0.25 < thr 1: no flow at all
    assert len(run(ev, gradient="savitzky_golay", mode="faithful")) == 0
    aee, _ = square_aee(run(ev, gradient="central", mode="faithful"), gt)
    assert aee > 10.0  # uncalibrated magnitudes


def blurred_edge(speed, angle_deg, n_per_pixel=3, spread_px=0.6, jitter_px=0.1, seed=0,
                 geometry=Geometry(40, 30, f=REFERENCE_FOCAL_PX), gap_px=4.0):
    """An ON edge of ``n_per_pixel`` events per pixel spread over ``spread_px`` of travel, with
    Gaussian timing jitter, followed ``gap_px`` behind by an OFF edge (polarities interleave)."""
    rng = np.random.default_rng(seed)
    a = np.radians(angle_deg)
    nx, ny = np.cos(a), np.sin(a)
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width]
    dist = (xs - geometry.cx) * nx + (ys - geometry.cy) * ny + 0.5 * np.hypot(*geometry.shape)
    cols = []
    for pol, lag in [(1, 0.0), (-1, gap_px)]:
        for j in range(n_per_pixel):
            d = dist + lag + spread_px * j / max(n_per_pixel - 1, 1)
            d = d + rng.normal(0, jitter_px, d.shape)
            cols.append((xs.ravel(), ys.ravel(), d.ravel() / speed * 1e6, np.full(d.size, pol)))
    x, y, t, p = (np.concatenate(c) for c in zip(*cols, strict=True))
    o = np.argsort(t, kind="stable")
    t = np.floor(t[o]).astype(np.int64)
    keep = t >= 0
    return EventPacket(geometry=geometry, t_start=0, t_end=int(t[-1]) + 1,
                       x=x[o][keep].astype(np.uint16), y=y[o][keep].astype(np.uint16),
                       t=t[keep], p=p[o][keep].astype(np.int8)), speed * nx, speed * ny


@pytest.mark.parametrize("gradient", list(GRADIENTS))
def test_calibrated_blurred_jittered_edges_with_both_polarities(gradient):
    """Several events per pixel, timing jitter of 0.1 px, ON and OFF edges interleaved:
    median speed within 5 % and median direction within 3 degrees (stated tolerance)."""
    for speed in [30.0, 300.0, 3000.0]:
        for angle in [0, 60, 200]:
            ev, vx, vy = blurred_edge(speed, angle)
            out = run(ev, gradient=gradient, window_us=max(80_000, int(8 / speed * 1e6)))
            s = np.hypot(out.vx, out.vy)
            ang = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(out.vy, out.vx)
                                                          - np.arctan2(vy, vx))))))
            where = f"{gradient} {speed} px/s {angle} deg"
            assert len(out) > 0.15 * len(ev), where  # refractory: one of 3 events per pixel
            assert np.all(np.isfinite(s))
            assert abs(np.median(s) / speed - 1) < 0.05, f"{where}: median {np.median(s)}"
            assert np.median(ang) < 3.0, f"{where}: median angle {np.median(ang)}"


def test_centre_check_removes_flow_from_an_older_crossing_edge():
    """Edge A sweeps right; edge B (same polarity) sweeps down through pixels A activated
    within the window, so their onsets are A's: without the centre check ~12 % of the flow
    points in neither edge's direction; with the default check none does."""
    g = Geometry(40, 30, f=REFERENCE_FOCAL_PX)
    a = moving_edge_events(300.0, 0.0, g, duration_us=200_000)
    b = moving_edge_events(0.0, 300.0, g, duration_us=200_000, offset_px=-3.0)
    ev = EventPacket.concat([a, b])
    ev = ev.select(np.argsort(ev.t, kind="stable"))

    def bad_share(out):
        ang = np.arctan2(out.vy, out.vx)
        good = (np.degrees(np.abs(ang)) < 10) | (np.degrees(np.abs(ang - np.pi / 2)) < 10)
        return 1 - good.mean()

    off = run(ev, gradient="central", refit_tolerance=0, centre_check_px=0)
    on = run(ev, gradient="central")
    assert bad_share(off) > 0.05
    assert bad_share(on) < 0.01 and len(on) > 0.8 * len(off)


@pytest.mark.parametrize("bad, says", [
    (dict(window_us=80_000, max_window_us=80_000), "must exceed window_us"),
    (dict(window_us=80_000, min_window_us=80_000), "must be shorter than window_us"),
    (dict(min_window_us=20_000, mode="faithful"), "calibrated mode only"),
    (dict(max_window_us=400_000, mode="faithful"), "calibrated mode only"),
])
def test_adaptive_window_bad_settings_are_refused(bad, says):
    with pytest.raises(ValueError, match=says):
        LKFlow.Params(**bad)
    LKFlow.Params(max_window_us=400_000, min_window_us=20_000)  # a valid setting passes


@pytest.mark.parametrize("scale", [1.0, 2.0, 0.5])
def test_windows_and_speeds_follow_the_focal_length(scale):
    """Left null, the windows and the refractory period are the reference camera's (80, 150,
    600 ms) over f / 380.6 px, the speed ceiling 1e5 px/s times it; the grid's lengths stay."""
    f = LKFlow()
    f.setup(LKFlow.Params(), Context())
    q = f.kernel_params(Geometry(int(320 * scale), int(240 * scale),
                                 f=scale * REFERENCE_FOCAL_PX))
    assert (q.window_us, q.refractory_us, q.max_window_us) == (
        round(80_000 / scale), round(150_000 / scale), round(600_000 / scale))
    assert q.max_speed_pxs == pytest.approx(1e5 * scale, rel=1e-12)
    assert (q.r, q.slow_px, q.centre_check_px) == (2, 3.0, 0.5)


def test_windows_given_are_kept():
    f = LKFlow()
    f.setup(LKFlow.Params(window_us=50_000, refractory_us=0, max_window_us=0,
                          max_speed_pxs=300.0), Context())
    q = f.kernel_params(Geometry(640, 480, f=2 * REFERENCE_FOCAL_PX))
    assert (q.window_us, q.refractory_us, q.max_window_us, q.max_speed_pxs) == (
        50_000, 0, 0, 300.0)
    f.setup(LKFlow.Params(mode="faithful"), Context())  # no adaptive window in faithful mode
    assert f.kernel_params(Geometry(640, 480, f=2 * REFERENCE_FOCAL_PX)).max_window_us == 0


@pytest.mark.parametrize("flow", ["lk_flow", "plane_flow"])
def test_flow_events_carry_their_edge_arrival(flow):
    """t_edge of each flow event is its pixel's run start over every event the stage saw,
    across packet cuts (the naive reference over the whole stream)."""
    from evchain.core.registry import make_registry
    from tests.naive.edge_arrival import arrivals

    g = Geometry(24, 18)
    # two slow ON edges 3 px apart (one run per pixel), then an OFF edge (new runs)
    edges = [moving_edge_events(6.0, 2.0, g, 8_000_000, pol, off)
             for pol, off in ((1, 0.0), (1, 3.0), (-1, 8.0))]
    ev = EventPacket.concat(edges)
    ev = ev.select(np.argsort(ev.t, kind="stable")).validate()
    f = make_registry().get(flow)()
    f.setup(f.Params(), Context(geometry=g))
    out = FlowPacket.concat([f.process(p) for p in recut([ev], [900_000, 2_500_000])])
    assert len(out) > 100
    key = list(zip(ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), ev.p.tolist(), strict=True))
    want = dict(zip(key, arrivals(key, 1_000_000), strict=True))
    got = [want[k] for k in zip(out.x.tolist(), out.y.tolist(), out.t.tolist(),
                                out.p.tolist(), strict=True)]
    np.testing.assert_array_equal(out.t_edge, got)
    # plane fitting gives the second edge flow (its events' arrival is the first edge's);
    # LK's window still holds the first edge there and gives it none
    assert np.sum(out.t_edge < out.t) == (280 if flow == "plane_flow" else 0)
