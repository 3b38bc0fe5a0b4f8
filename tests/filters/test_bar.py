"""Source ``bar``, its ground truth and the timing scorer helper against the emulator."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import EventPacket
from evchain.filters.bar import BarSource
from evchain.filters.emulator import Emulator
from evchain.report.timing import timing_errors
from evchain.sim.bar import Bar, BarTruth
from evchain.testing.contract import check_source


def test_source_contract_defaults():
    packets = check_source(BarSource, {})
    assert packets[0].frames.shape[1:] == (48, 64)
    assert packets[0].t_start == 0 and packets[-1].t_end == 200_000


def test_sharp_edge_is_exact_pixel_area():
    bar = Bar(width=40, height=1, bar_width_px=7.3, x0_px=20.25, edge="sharp", speed_pxs=100)
    f = bar.fraction(np.arange(40), 0.0)
    assert f.sum() == pytest.approx(7.3)
    assert f.max() == 1.0 and f.min() == 0.0
    assert f[20] == pytest.approx(0.75) and f[13] == pytest.approx(0.55)   # trailing edge at 12.95


@pytest.mark.parametrize("edge", ["linear", "sigmoid", "erf"])
def test_gradual_edges_are_monotone_and_symmetric(edge):
    bar = Bar(width=80, height=1, bar_width_px=30, x0_px=50, edge=edge, edge_width_px=4)
    f = bar.fraction(np.arange(80) + 0.0, 0.0)
    centre = 50 - 15
    assert np.all(np.diff(f[:centre + 1]) >= 0) and np.all(np.diff(f[centre:]) <= 0)
    np.testing.assert_allclose(f[centre - 10:centre], f[centre + 10:centre:-1], atol=1e-12)


def test_flow_truth():
    truth = BarTruth(Bar(width=64, height=4, bar_width_px=16, x0_px=30, edge="sharp",
                         speed_pxs=200))
    vx, vy = truth.flow(np.array([5, 20, 30, 60]), np.zeros(4), np.zeros(4))
    np.testing.assert_array_equal(vx, [0, 200, 200, 0])
    np.testing.assert_array_equal(vy, 0)
    from evchain.core.truth import FlowTruth, FoeTruth, TtcTruth

    assert isinstance(truth, FlowTruth)
    assert not isinstance(truth, FoeTruth) and not isinstance(truth, TtcTruth)  # no FOE, no TTC


def emulate_bar(params, emu, seed=0):
    ctx = Context(seed=seed)
    src = BarSource()
    src.setup(BarSource.Params(**params), ctx)
    f = Emulator()
    f.record_float_times = True
    f.setup(Emulator.Params(**emu), ctx)
    outs = [f.process(p) for p in src.packets()]
    outs.append(f.flush())
    ev = EventPacket.concat(outs).validate()
    return ev, np.concatenate(f.float_times), src, f


BAR = dict(width=64, height=3, bar_width_px=16, speed_pxs=200, x0_px=10, edge="erf",
           edge_width_px=2, duration_us=250_000, dt_us=1000, frames_per_packet=40)


def test_emulator_timing_against_analytic_crossings():
    res = {}
    for interp in ("linear", "cubic"):
        ev, tf, src, f = emulate_bar(BAR, dict(interpolation=interp, threshold_on=0.2,
                                               threshold_off=0.2))
        t = src.frame_times()
        truth = src.truth.crossing_times(0.2, 0.2, 1e-3, t[0], t[-1])
        assert len(truth) > 1000
        res[interp] = timing_errors(ev.x, ev.y, ev.p, tf, truth, 64)
        assert res[interp]["count_diff"] == 0 and res[interp]["unmatched"] == 0
        rounded = timing_errors(ev.x, ev.y, ev.p, ev.t, truth, 64)
        assert abs(rounded["median_abs_dt_us"] - res[interp]["median_abs_dt_us"]) < 0.6
    assert res["cubic"]["median_abs_dt_us"] < 0.5
    assert res["linear"]["median_abs_dt_us"] > 2 * res["cubic"]["median_abs_dt_us"]
    assert res["cubic"]["max_abs_dt_us"] < 50


def test_crossings_with_mismatch_and_thesis_mapping():
    emu = dict(interpolation="cubic", threshold_on=30, threshold_off=30,
               log_mapping="thesis8bit", mismatch_sigma=0.05)
    ev, tf, src, f = emulate_bar({**BAR, "edge": "sigmoid", "edge_width_px": 6}, emu)
    con, coff = f.thresholds
    c_on, c_off, eps = f.natural_parameters()
    t = src.frame_times()
    truth = src.truth.crossing_times(con, coff, eps, t[0], t[-1])
    r = timing_errors(ev.x, ev.y, ev.p, tf, truth, 64)
    assert r["count_diff"] == 0 and r["n_matched"] > 200
    assert r["median_abs_dt_us"] < 0.5
    # kinked profiles (linear ramp): counts still exact, timing limited by the kinks
    ev, tf, src, f = emulate_bar({**BAR, "edge": "linear", "edge_width_px": 6}, emu)
    truth = src.truth.crossing_times(*f.thresholds, eps, t[0], t[-1])
    assert timing_errors(ev.x, ev.y, ev.p, tf, truth, 64)["count_diff"] == 0


def test_timing_errors_helper():
    truth = np.zeros(4, dtype=[("x", "i8"), ("y", "i8"), ("t", "f8"), ("p", "i1")])
    truth["x"] = [1, 1, 1, 2]
    truth["t"] = [10.0, 20.0, 30.0, 5.0]
    truth["p"] = [1, 1, -1, 1]
    r = timing_errors(np.array([1, 1, 1]), np.zeros(3), np.array([1, -1, 1]),
                      np.array([11.0, 30.5, 23.0]), truth, width=4)
    assert r["n_matched"] == 3 and r["count_diff"] == -1 and r["unmatched"] == 1
    assert r["max_abs_dt_us"] == 3.0 and r["median_abs_dt_us"] == 1.0
