"""plane_flow filter: contract, density series, DVSFLOW16 translating square."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evchain.core.camera_scale import REFERENCE_FOCAL_PX
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.core.series import FLOW_DENSITY
from evchain.filters.flow_scorer import score_flow
from evchain.filters.plane_flow import PlaneFlow
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import moving_edge_events, random_events

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dvsflow16"
VARIANTS = ["single", "iterative", "robust", "original", "savitzky_golay"]


def edge_stream() -> list[EventPacket]:
    g = Geometry(48, 36, f=REFERENCE_FOCAL_PX)
    edge = moving_edge_events(120.0, 70.0, g, duration_us=400_000)
    off = moving_edge_events(-60.0, 20.0, g, duration_us=400_000, polarity=-1)
    noise = random_events(400, g, 0, 400_000, seed=3)
    cols = {c: np.concatenate([getattr(a, c) for a in (edge, off, noise)])
            for c in EventPacket.columns}
    merged = EventPacket(geometry=g, t_start=0, t_end=400_000, **cols)
    merged = merged.select(np.argsort(merged.t, kind="stable"))
    return recut([merged], [70_000, 150_000, 260_000])


@pytest.mark.parametrize("variant", VARIANTS)
def test_contract(variant, tmp_path):
    out = check_filter(PlaneFlow, {"variant": variant, "refractory_us": 20_000,
                                   "window_us": 60_000, "max_speed_pxs": 5000.0},
                       edge_stream(), out_dir=tmp_path)
    assert len(out["t"]) > 50
    assert np.isfinite(out["vx"]).all() and np.isfinite(out["vy"]).all()
    dens = out[f"series:{FLOW_DENSITY.name}"]
    n_in = sum(len(p) for p in edge_stream())
    assert dens["n_in"].sum() == n_in
    assert dens["n_out"].sum() == len(out["t"])
    assert np.all(np.diff(dens["t"]) > 0) and np.all(dens["t"] % 100_000 == 0)


def test_defaults_run(tmp_path):
    out = check_filter(PlaneFlow, {}, edge_stream(), out_dir=tmp_path)
    assert len(out["t"]) > 0


#: jAER's refractory and the fixed window these tests were written for (the defaults keep each
#: burst's onset and adapt the window to slow edges)
JAER = {"refractory_us": 150_000, "refractory_updates": True, "max_window_us": 0}


def run(packets, **params):
    f = PlaneFlow()
    f.setup(PlaneFlow.Params(**{**JAER, **params}), Context(geometry=packets[0].geometry))
    outs = [f.process(p) for p in packets]
    last = f.flush()
    return outs + ([last] if last is not None else [])


def test_edge_velocity_through_filter():
    g = Geometry(48, 36, f=REFERENCE_FOCAL_PX)
    ev = moving_edge_events(-150.0, 80.0, g, duration_us=300_000)
    for variant in ("single", "iterative", "robust", "savitzky_golay"):
        outs = run(recut([ev], [100_000, 200_000]), variant=variant, refractory_us=0,
                   window_us=40_000)
        vx = np.concatenate([o.vx for o in outs])
        vy = np.concatenate([o.vy for o in outs])
        assert len(vx) > 0.7 * len(ev)
        np.testing.assert_allclose(vx, -150.0, rtol=0.02)
        np.testing.assert_allclose(vy, 80.0, rtol=0.02)


def test_refractory_lowers_density():
    packets = edge_stream()
    n0 = sum(len(o) for o in run(packets, refractory_us=0))
    n1 = sum(len(o) for o in run(packets, refractory_us=300_000))
    assert 0 < n1 <= n0


def test_empty_stream():
    g = Geometry(20, 10, f=REFERENCE_FOCAL_PX)
    outs = run([EventPacket.empty(g, 0, 1000), EventPacket.empty(g, 1000, 5000)])
    assert [len(o) for o in outs] == [0, 0, 0]
    assert outs[-1].t_start == outs[-1].t_end == 5000
    assert all(len(o.series[FLOW_DENSITY.name]) == 0 for o in outs)


@pytest.mark.skipif(not (DATA / "TranslatingSquare.aedat").is_file(),
                    reason="DVSFLOW16 data not available in ../shared/data/dvsflow16")
@pytest.mark.parametrize("variant", ["single", "iterative", "robust", "savitzky_golay"])
def test_dvsflow16_square(variant):
    """The translating square (20 px/s, equal timestamps along each edge): AEE against the
    ground truth stays a few px/s (corners of the square carry most of the error)."""
    from evchain.io.aedat2 import read_aedat2
    from evchain.io.dvsflow16 import DVSFLOW16Truth

    ev = read_aedat2(DATA / "TranslatingSquare.aedat", chip="davis240")
    truth = DVSFLOW16Truth(DATA / "gtTranslatingSquare.mat", 180, 240)
    outs = run(recut([ev], [1_000_000, 2_500_000, 2_500_001]), variant=variant,
               window_us=100_000, refractory_us=0)
    x, y, t, vx, vy = (np.concatenate([getattr(o, c) for o in outs])
                       for c in ("x", "y", "t", "vx", "vy"))
    assert np.isfinite(vx).all() and np.isfinite(vy).all()
    m = score_flow(x, y, t, vx, vy, truth)
    assert m["n_scored"] >= 140  # of the 160 events of the step inside the validity window
    assert m["aee_pxs"] < 2.5
    assert m["aae_deg"] < 3.0
    # the median event is exact: 20 px/s along the edge normal
    assert np.median(np.hypot(vx, vy)) == pytest.approx(20.0, rel=1e-3)


@pytest.mark.parametrize("bad, says", [
    (dict(window_us=80_000, max_window_us=80_000), "must exceed window_us"),
    (dict(window_us=80_000, min_window_us=80_000), "must be shorter than window_us"),
    (dict(min_window_us=20_000, variant="original"), "does not apply to variant original"),
    (dict(max_window_us=400_000, variant="original"), "does not apply to variant original"),
])
def test_adaptive_window_bad_settings_are_refused(bad, says):
    with pytest.raises(ValueError, match=says):
        PlaneFlow.Params(**bad)
    PlaneFlow.Params(max_window_us=400_000, min_window_us=10_000)  # a valid setting passes


@pytest.mark.parametrize("scale", [1.0, 2.0, 0.5])
def test_windows_and_speeds_follow_the_focal_length(scale):
    """Left null, the windows and the plane's time limit are the reference camera's (80, 500 ms,
    4 ms) over f / 380.6 px, the speed ceiling 1000 px/s times it; the grid's lengths and the
    refractory period (350 ms) stay."""
    f = PlaneFlow()
    f.setup(PlaneFlow.Params(), Context())
    q = f.kernel_params(Geometry(int(320 * scale), int(240 * scale),
                                 f=scale * REFERENCE_FOCAL_PX))
    assert (q.window_us, q.max_window_us, q.refractory_us) == (
        round(80_000 / scale), round(500_000 / scale), 350_000)
    assert q.th2 == pytest.approx(0.004 / scale, rel=1e-12)
    assert q.max_speed == pytest.approx(1000.0 * scale, rel=1e-12)
    assert (q.r, q.margin, q.slow_px, q.refractory_updates) == (2, 2, 2.0, False)


def test_windows_given_are_kept():
    f = PlaneFlow()
    f.setup(PlaneFlow.Params(window_us=50_000, refractory_us=0, max_window_us=0, th2_s=0.01,
                             max_speed_pxs=300.0), Context())
    q = f.kernel_params(Geometry(640, 480, f=2 * REFERENCE_FOCAL_PX))
    assert (q.window_us, q.refractory_us, q.max_window_us, q.th2, q.max_speed) == (
        50_000, 0, 0, 0.01, 300.0)


def test_metrics_say_why_events_got_no_flow():
    """metrics.plane_flow counts every event once: the flow events, and for the rest the
    reason (refractory, border, too few neighbours ...); the same over any packet cuts. An empty
    stream reports zeros."""
    reports = []
    for cuts in ([70_000, 150_000, 260_000], [10_000, 300_000]):
        packets = recut(edge_stream(), cuts)
        f = PlaneFlow()
        ctx = Context(geometry=packets[0].geometry)
        f.setup(PlaneFlow.Params(refractory_us=20_000, window_us=60_000), ctx)
        n_flow = sum(len(f.process(p)) for p in packets)
        f.flush()
        m = ctx.metrics["plane_flow"]
        assert m["events"] == sum(len(p) for p in packets)
        assert m["flow_events"] == n_flow > 0
        assert m["events"] == m["flow_events"] + sum(m["no_flow"].values())
        assert m["no_flow"]["refractory"] > 0 and m["no_flow"]["border"] > 0
        reports.append(m)
    assert reports[0] == reports[1]
    f = PlaneFlow()
    ctx = Context(geometry=Geometry(8, 6))
    f.setup(PlaneFlow.Params(), ctx)
    f.flush()
    assert ctx.metrics["plane_flow"]["events"] == 0
    assert set(ctx.metrics["plane_flow"]["no_flow"].values()) == {0}
