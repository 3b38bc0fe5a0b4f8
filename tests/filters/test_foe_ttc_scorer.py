"""foe_ttc_scorer: exact metrics on constructed estimates, pictures, contract."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.series import FOE_ERROR, TTC, TTC_CLUSTERS
from evchain.errors import ConfigError
from evchain.filters.foe_map import FoeMap, foe_series
from evchain.filters.foe_ttc_scorer import FoeTtcScorer, foe_angle_deg
from evchain.filters.ttc import Ttc
from evchain.testing.contract import check_filter
from evchain.testing.synthetic import ExpansionTruth, expansion_stream
from tests.naive.foe_map import expansion_packets
from tests.naive.ttc import PX

G = Geometry(128, 96, f=100.0)
FOE = (60.0, 40.0)


def stream(dx=0.0, dy=0.0, tau_factor=1.0, t_collision=4.0, gap=None, at=None):
    """Empty flow packets of 100 ms carrying a foe estimate (true + offset) and a ttc estimate
    (true * factor) every 10 ms; ``gap`` = (t0, t1) in s without ttc estimates; ``at``: the
    reported cluster's centre (x, y) as a function of t in s (default (60, 60))."""
    out = []
    for k in range(int(t_collision * 10) - 1):
        t0 = k * 100_000
        t = np.arange(t0, t0 + 100_000, 10_000, dtype=np.int64)
        tau = (t_collision - t * 1e-6) * tau_factor
        keep = np.ones(len(t), bool) if gap is None else ~((t >= gap[0] * 1e6)
                                                          & (t < gap[1] * 1e6))
        cx, cy = (60.0, 60.0) if at is None else at(t[keep] * 1e-6)
        ttc = TTC.array(t=t[keep], tau_s=tau[keep], cluster=np.ones(keep.sum()),
                        x=np.broadcast_to(cx, keep.sum()), y=np.broadcast_to(cy, keep.sum()),
                        support=np.ones(keep.sum()))
        p = FlowPacket.empty(G, t0, t0 + 100_000)
        p = p.with_series("foe", foe_series(np.full(len(t), FOE[0] + dx),
                                            np.full(len(t), FOE[1] + dy), t, np.ones(len(t))))
        out.append(p.with_series("ttc", ttc))
    return out, ExpansionTruth(FOE, t_collision)


def score(packets, truth, tmp_path, **params):
    ctx = Context(out_dir=tmp_path, truth=truth)
    f = FoeTtcScorer()
    # the margin these tests were written with (null: 1 px on this small sensor)
    f.setup(FoeTtcScorer.Params(**{"plots": False, "obstacle_margin_px": 2, **params}), ctx)
    outs = [f.process(p) for p in packets]
    f.flush()
    f.close()
    return ctx.metrics, FlowPacket.concat(outs)


def test_perfect_estimates(tmp_path):
    m, out = score(*stream(), tmp_path)
    assert m["foe"]["dx_mean_px"] == 0 and m["foe"]["dy_std_px"] == 0
    assert m["foe"]["angle_mean_deg"] == pytest.approx(0, abs=1e-6)
    assert m["ttc"]["median_rel_error_last3s"] == pytest.approx(0, abs=1e-12)
    assert m["ttc"]["share_within_10pct"] == 1.0 and m["ttc"]["share_within_20pct"] == 1.0
    assert len(out.series["foe_error"]) == len(out.series["foe"])
    assert len(out.series["ttc_error"]) == len(out.series["ttc"])


def test_offsets_and_bias(tmp_path):
    m, _ = score(*stream(dx=3.0, dy=-1.5, tau_factor=1.15), tmp_path)
    assert m["foe"]["dx_mean_px"] == pytest.approx(3.0)
    assert m["foe"]["dy_mean_px"] == pytest.approx(1.5)
    assert m["foe"]["dx_std_px"] == pytest.approx(0.0, abs=1e-12)
    a = np.array([63.0 - G.cx, 38.5 - G.cy, 100.0])   # rays with f = 100 through the
    b = np.array([60.0 - G.cx, 40.0 - G.cy, 100.0])   # estimated and the true FOE
    want = math.degrees(math.acos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    assert m["foe"]["angle_mean_deg"] == pytest.approx(want, rel=1e-9)
    assert float(foe_angle_deg(63.0, 38.5, 60.0, 40.0, 100.0, G.cx, G.cy)) == pytest.approx(want)
    assert m["ttc"]["median_rel_error_last3s"] == pytest.approx(0.15)
    assert m["ttc"]["share_within_10pct"] == 0.0 and m["ttc"]["share_within_20pct"] == 1.0


def test_warmup_and_missing_estimates(tmp_path):
    # a one-second gap inside the last 3 s counts as misses
    m, _ = score(*stream(gap=(2.0, 3.0)), tmp_path, warmup_s=2.5)
    assert m["foe"]["n"] == len(np.arange(2_500_000, 3_900_000, 10_000))
    share = m["ttc"]["share_within_10pct"]
    assert 0.6 < share < 0.72          # about 1 s of 2.9 s missing
    assert m["ttc"]["coverage_last3s"] == pytest.approx(share)


@pytest.mark.parametrize(("width", "focal", "margin"), [(320, 380.6, 2), (640, 761.2, 4),
                                                      (128, 100.0, 1)])
def test_obstacle_margin_follows_the_focal_length(width, focal, margin):
    """Left null, the obstacle margin is 2 px on the reference camera times f / 380.6 px,
    rounded; a value given is kept."""
    f = FoeTtcScorer()
    f.setup(FoeTtcScorer.Params(plots=False), Context(truth=ExpansionTruth(FOE, 1.0)))
    f._geometry = Geometry(width, width * 3 // 4, f=focal)
    assert f._margin() == margin
    f.setup(FoeTtcScorer.Params(plots=False, obstacle_margin_px=3),
            Context(truth=ExpansionTruth(FOE, 1.0)))
    f._geometry = Geometry(640, 480, f=761.2)
    assert f._margin() == 3


def test_without_truth_fails_at_setup(tmp_path):
    packets, _ = stream()
    with pytest.raises(ConfigError, match=r"stage 'foe_ttc_scorer' needs ground truth with FOE "
                       r"\(FoeTruth\), TTC \(TtcTruth\), but the source provides no ground truth"):
        score(packets, None, tmp_path)


def test_whole_chain_writes_pictures(tmp_path):
    truth = ExpansionTruth(FOE, 1.6)
    packets = expansion_packets(foe=FOE, tau_s=1.6, n=60_000, geometry=G,
                                duration_us=1_500_000, n_packets=15, tau_shrinks=True,
                                normal_only=True)
    ctx = Context(out_dir=tmp_path, truth=truth)
    chain = [FoeMap(), Ttc(), FoeTtcScorer()]
    for f in chain:  # random points with exact flow, no moving edges: ttc's tau from the flow
        f.setup(f.Params(**({**PX, "baseline_px": 0} if isinstance(f, Ttc) else {})), ctx)
    for p in packets:
        for f in chain:
            p = f.process(p)
    for f in chain:
        f.flush()
    assert ctx.metrics["ttc"]["median_rel_error_last3s"] < 0.05
    assert ctx.metrics["foe"]["dx_mean_px"] < 1.0
    names = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert names == ["foe_error.png", "snapshot_end.png", "snapshot_ttc0.3s.png",
                     "snapshot_ttc1s.png", "ttc.png"]
    assert all((tmp_path / "plots" / n).read_bytes()[:4] == b"\x89PNG" for n in names)


def test_contract(tmp_path):
    packets, truth = stream(t_collision=1.0)
    check_filter(FoeTtcScorer, {"plots": False}, packets, truth=truth, out_dir=tmp_path)
    packets, truth = expansion_stream(foe_series=True)
    check_filter(FoeTtcScorer, {}, packets, truth=truth, out_dir=tmp_path)


class ObjectTruth(ExpansionTruth):
    """The expansion's truth plus objects: the obstacle (box 7) is seen inside a rectangle that
    moves right at 5 px/s (x from 20 + 5 t to 40 + 5 t, y from 20 to 40, t in s), a roadside
    post (box 3) at x >= 55, the ground elsewhere. Records the size of every query."""

    def __init__(self, t_collision_s: float, obstacle_ids=(7,)):
        super().__init__(FOE, t_collision_s)
        self.obstacle_ids = np.array(obstacle_ids, np.int64)
        self.calls: list[int] = []

    def object_id(self, x, y, t_us):
        x, y, t = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float),
                                      np.asarray(t_us, float) * 1e-6)
        self.calls.append(x.size)
        car = (x >= 20 + 5 * t) & (x <= 40 + 5 * t) & (y >= 20) & (y <= 40)
        return np.where(car, 7, np.where(x >= 55, 3, -2)).astype(np.int64)


def on_car(t_s):
    """The centre of the obstacle's rectangle at t_s."""
    return 30.0 + 5.0 * t_s, 30.0


WINDOW = 301       # grid times 0.89 .. 3.89 s of the 3.9 s stream (every 10 ms)


def test_off_obstacle_match_counts_only_in_plain_share(tmp_path):
    """A roadside cluster whose tau equals the true TTC: a hit for share_within_20pct, never
    on the obstacle."""
    packets, _ = stream()
    m, out = score(packets, ObjectTruth(4.0), tmp_path)
    t = m["ttc"]
    assert t["share_within_20pct"] == 1.0
    assert t["share_on_obstacle_within_20pct"] == 0.0 and t["coverage_on_obstacle"] == 0.0
    assert t["median_rel_error_on_obstacle"] is None
    assert (out.series["ttc_error"]["on_obstacle"] == 0).all()


def test_on_obstacle_within_20pct_counts(tmp_path):
    """A cluster following the moving obstacle (queried at each grid time: at time 0 the
    rectangle would have missed it after 2 s)."""
    truth = ObjectTruth(4.0)
    m, out = score(*stream(tau_factor=1.15, at=on_car)[:1], truth, tmp_path)
    t = m["ttc"]
    assert t["share_on_obstacle_within_20pct"] == 1.0 and t["coverage_on_obstacle"] == 1.0
    assert t["median_rel_error_on_obstacle"] == pytest.approx(0.15)
    assert list(t["bias_on_obstacle_by_ttc"]) == ["0-500ms", "500-1000ms", "1000-2000ms",
                                                  "2000-3000ms"]
    assert t["bias_on_obstacle_by_ttc"]["0-500ms"] == pytest.approx(0.15)
    assert t["bias_on_obstacle_by_ttc"]["2000-3000ms"] == pytest.approx(0.15)
    assert (out.series["ttc_error"]["on_obstacle"] == 1).all()
    assert out.series["ttc_error"]["on_obstacle"].dtype == np.int8
    # vectorised: one query of 5 x 5 positions per packet's 10 ticks, one for the window
    assert truth.calls == [25 * 10] * 39 + [25 * WINDOW]
    m, _ = score(*stream(tau_factor=1.3, at=on_car)[:1], ObjectTruth(4.0), tmp_path)
    t = m["ttc"]
    assert t["share_on_obstacle_within_20pct"] == 0.0 and t["coverage_on_obstacle"] == 1.0
    assert t["median_rel_error_on_obstacle"] == pytest.approx(0.3)
    m, _ = score(*stream(tau_factor=0.7, at=on_car)[:1], ObjectTruth(4.0), tmp_path)
    assert all(v == pytest.approx(-0.3) for v in m["ttc"]["bias_on_obstacle_by_ttc"].values())


def test_obstacle_margin(tmp_path):
    """A centre 2 px beside the obstacle's outline is on it with the default margin (2), not
    with 0; 3 px beside it is off."""
    def beside(gap):
        return lambda t_s: (40.0 + 5.0 * t_s + gap, 30.0)

    cov = {}
    for gap, margin in ((2.0, 2), (2.0, 0), (3.0, 2)):
        m, _ = score(*stream(at=beside(gap))[:1], ObjectTruth(4.0), tmp_path,
                     obstacle_margin_px=margin)
        cov[gap, margin] = m["ttc"]["coverage_on_obstacle"]
    assert cov == {(2.0, 2): 1.0, (2.0, 0): 0.0, (3.0, 2): 0.0}


def test_on_obstacle_part_of_the_window(tmp_path):
    """Off the obstacle (but right) before 2.5 s, on it after: the share on the obstacle is
    the share of grid times from 2.5 s on."""
    def moving(t_s):
        x, y = on_car(t_s)
        return np.where(t_s >= 2.5, x, 60.0), y

    m, out = score(*stream(at=moving)[:1], ObjectTruth(4.0), tmp_path)
    t = m["ttc"]
    assert t["share_within_20pct"] == 1.0
    assert t["share_on_obstacle_within_20pct"] == pytest.approx(140 / WINDOW)
    assert t["coverage_on_obstacle"] == pytest.approx(140 / WINDOW)
    err = out.series["ttc_error"]
    np.testing.assert_array_equal(err["on_obstacle"], err["t"] >= 2_500_000)
    # on the obstacle from a true TTC of 1.5 s: the far bin has no times on it
    bias = t["bias_on_obstacle_by_ttc"]
    assert bias["2000-3000ms"] is None and bias["1000-2000ms"] == pytest.approx(0.0, abs=1e-9)


def test_stale_estimates_on_obstacle_count_as_misses(tmp_path):
    m, _ = score(*stream(at=on_car, gap=(2.0, 3.0))[:1], ObjectTruth(4.0), tmp_path)
    t = m["ttc"]
    assert 0.6 < t["share_on_obstacle_within_20pct"] < 0.72      # about 1 s of 3 s missing
    assert t["share_on_obstacle_within_20pct"] == t["coverage_on_obstacle"] \
        == t["coverage_last3s"]


@pytest.mark.parametrize("truth", [ExpansionTruth(FOE, 4.0), ObjectTruth(4.0, obstacle_ids=())],
                         ids=["no object_id", "no obstacle"])
def test_truth_without_objects_gives_none(tmp_path, truth):
    m, out = score(*stream(at=on_car)[:1], truth, tmp_path)
    t = m["ttc"]
    assert t["share_within_20pct"] == 1.0
    keys = ("share_on_obstacle_within_20pct", "coverage_on_obstacle",
            "median_rel_error_on_obstacle", "misses", "bias_on_obstacle_by_ttc")
    for key in keys:
        assert key in t and t[key] is None
    assert (out.series["ttc_error"]["on_obstacle"] == -1).all()
    if isinstance(truth, ObjectTruth):     # knows objects, but there is no obstacle
        assert "not_scored" not in t
    else:                                  # cannot tell: says what it could not score
        assert t["not_scored"] == (", ".join(keys) + ": the ground truth (ExpansionTruth) has "
                                   "no object ids (ObjectTruth)")


def test_ttc_plot_on_and_off_the_obstacle(tmp_path):
    truth = ObjectTruth(4.0)
    m, _ = score(*stream(at=lambda t_s: (np.where(t_s >= 2.5, 30.0 + 5.0 * t_s, 60.0), 30.0)
                         )[:1], truth, tmp_path, plots=True)
    assert (tmp_path / "plots" / "ttc.png").read_bytes()[:4] == b"\x89PNG"
    packets, _ = stream(t_collision=1.0, at=on_car)
    check_filter(FoeTtcScorer, {"plots": False}, packets, truth=ObjectTruth(1.0),
                 out_dir=tmp_path)


@pytest.mark.parametrize("delay_ms", [0.0, 70.0, 133.0, -40.0])
def test_foe_lag_finds_the_delay_of_a_delayed_series(delay_ms):
    from evchain.filters.foe_ttc_scorer import foe_lag_ms

    t = np.arange(0, 6_000_000, 10_000, dtype=np.int64)
    true = lambda tt: 120 + 5 * np.sin(2 * np.pi * tt * 1e-6 / 1.3) \
        + 2 * np.sin(2 * np.pi * tt * 1e-6 / 0.37)  # noqa: E731
    rng = np.random.default_rng(3)
    est = true(t - delay_ms * 1000) + rng.normal(0, 0.5, len(t))
    assert foe_lag_ms(t, est, true(t)) == pytest.approx(delay_ms, abs=3.0)


def test_foe_lag_is_undefined_where_the_truth_does_not_move():
    from evchain.filters.foe_ttc_scorer import foe_lag_metrics, foe_lag_ms

    t = np.arange(0, 3_000_000, 10_000, dtype=np.int64)
    rng = np.random.default_rng(4)
    assert foe_lag_ms(t, 100 + rng.normal(0, 2, len(t)), np.full(len(t), 100.0)) is None
    foe = np.zeros(len(t), FOE_ERROR.dtype)
    foe["t"], foe["x_true"], foe["y_true"] = t, 80.0, 60 + 4 * np.sin(t * 1e-6 * 5)
    foe["x"], foe["y"] = 80.5, 60 + 4 * np.sin((t - 50_000) * 1e-6 * 5)
    m = foe_lag_metrics(foe)
    assert m["lag_axis"] == "y" and m["lag_ms"] == pytest.approx(50.0, abs=2.0)


class RotatingTruth(ExpansionTruth):
    """The expansion seen by a camera turning at (0.1, -0.2 sin t, 0) rad/s."""

    def angular_velocity(self, t_us):
        t = np.asarray(t_us, np.float64) * 1e-6
        return np.full(t.shape, 0.1), -0.2 * np.sin(t), np.zeros(t.shape)


def with_rotation(packets, offset_deg_s, every=1):
    """The packets' foe entries with the true rotation plus ``offset_deg_s`` (3 values) on every
    ``every``-th entry and none (``rotation`` 0) on the others."""
    out = []
    for p in packets:
        foe = p.series["foe"].copy()
        t = foe["t"] * 1e-6
        w = np.degrees(np.stack([np.full(t.shape, 0.1), -0.2 * np.sin(t), np.zeros(t.shape)], 1))
        w = w + np.asarray(offset_deg_s)
        est = np.arange(len(t)) % every == 0
        w[~est] = 0.0
        for i, c in enumerate(("wx_deg_s", "wy_deg_s", "wz_deg_s")):
            foe[c] = w[:, i]
        foe["rotation"] = est
        out.append(p.replace(series={**p.series, "foe": foe}))
    return out


def test_rotation_rate_error(tmp_path):
    packets, _ = stream()
    truth = RotatingTruth(FOE, 4.0)
    m, out = score(with_rotation(packets, (3.0, -4.0, 0.0), every=2), truth, tmp_path)
    f = m["foe"]
    assert f["rotation_rate_error_deg_s"] == pytest.approx(5.0)
    assert f["rotation_rate_error_wx_deg_s"] == pytest.approx(3.0)
    assert f["rotation_rate_error_wy_deg_s"] == pytest.approx(4.0)
    assert f["rotation_rate_error_wz_deg_s"] == pytest.approx(0.0, abs=1e-9)
    assert f["rotation_coverage"] == pytest.approx(0.5, abs=0.01)
    t = np.arange(1_000_000, 3_900_000, 10_000) * 1e-6           # after the warm-up
    want = np.median(np.degrees(np.hypot(0.1, 0.2 * np.sin(t))))
    assert f["rotation_rate_true_deg_s"] == pytest.approx(want, rel=0.02)
    err = out.series["foe_error"]
    est = np.arange(len(err)) % 10 % 2 == 0  # every other entry of each packet's ten
    np.testing.assert_allclose(err["rotation_error_deg_s"][est], 5.0)
    assert (err["rotation_error_deg_s"][~est] == -1).all()
    np.testing.assert_allclose(err["wx_true_deg_s"], np.degrees(0.1))
    assert "why_none" not in f


def test_rotation_not_estimated_or_not_known(tmp_path):
    packets, truth = stream()          # foe_map's entries carry no rotation
    f = score(packets, RotatingTruth(FOE, 4.0), tmp_path)[0]["foe"]
    assert f["rotation_rate_error_deg_s"] is None and f["rotation_coverage"] == 0.0
    assert "not_scored" not in f
    assert set(f["why_none"]) == {"rotation_rate_error_deg_s", "rotation_rate_error_wx_deg_s",
                                  "rotation_rate_error_wy_deg_s",
                                  "rotation_rate_error_wz_deg_s", "rotation_rate_true_deg_s"}
    assert f["why_none"]["rotation_rate_error_deg_s"].startswith("no scored FOE estimate")

    class NoRotation:                  # a truth that knows FOE and TTC only
        foe, ttc = truth.foe, truth.ttc

    f = score(with_rotation(packets, (1.0, 0.0, 0.0)), NoRotation(), tmp_path)[0]["foe"]
    assert f["rotation_rate_error_deg_s"] is None and f["rotation_coverage"] is None
    assert f["not_scored"].endswith("has no camera rotation (RotationTruth)")
    assert f["why_none"]["rotation_coverage"] == f["not_scored"]
    assert f["dx_mean_px"] == 0


# -- hard cases: short streams, no estimates, no obstacle ------------------------------------


def score_ctx(packets, truth, tmp_path, **params):
    """Like :func:`score`, also returning the context (its warnings)."""
    ctx = Context(out_dir=tmp_path, truth=truth)
    f = FoeTtcScorer()
    # the margin these tests were written with (null: 1 px on this small sensor)
    f.setup(FoeTtcScorer.Params(**{"plots": False, "obstacle_margin_px": 2, **params}), ctx)
    outs = [f.process(p) for p in packets]
    f.flush()
    return ctx, FlowPacket.concat(outs)


def test_full_windows_say_their_length_and_warn_nothing(tmp_path):
    ctx, _ = score_ctx(*stream(), tmp_path)
    assert ctx.metrics["ttc"]["window_s"] == pytest.approx(3.0)
    assert ctx.metrics["ttc"]["window_span_s"] == pytest.approx([0.89, 3.89])
    assert ctx.metrics["foe"]["window_s"] == pytest.approx(2.9)   # 1 s warm-up of 3.9 s
    assert ctx.warnings == []


def test_a_stream_shorter_than_the_ttc_window_says_so(tmp_path):
    """The last 1.2 s of a drive: the TTC window is those 1.2 s, not 3, and a warning says
    so; the metrics are those of the 1.2 s."""
    packets, truth = stream()
    ctx, _ = score_ctx(packets[-12:], truth, tmp_path, warmup_s=0.5)
    t = ctx.metrics["ttc"]
    assert t["window_s"] == pytest.approx(1.19)
    assert t["window_span_s"] == pytest.approx([2.7, 3.89])
    assert t["share_within_20pct"] == 1.0
    assert ctx.metrics["foe"]["window_s"] == pytest.approx(0.7)
    assert len(ctx.warnings) == 1
    assert "TTC window is 1.19 s, shorter than last_window_s 3 s" in ctx.warnings[0]


def test_a_stream_under_the_foe_warmup_scores_no_foe_and_says_why(tmp_path):
    packets, truth = stream()
    ctx, _ = score_ctx(packets[-5:], truth, tmp_path, warmup_s=1.0)
    f = ctx.metrics["foe"]
    assert f["n"] == 0 and f["window_s"] == 0.0 and f["dx_mean_px"] is None
    assert "not longer than the FOE warm-up" in f["why_none"]
    assert any("FOE warm-up" in w for w in ctx.warnings)
    assert any("TTC window is 0.49 s" in w for w in ctx.warnings)


def test_no_estimates_give_none_medians_with_reasons(tmp_path):
    """TTC estimates at under half of the window's times: the medians (a miss is an
    infinite error) are None, not infinite, and why_none says why; no FOE at all: None and a
    reason."""
    packets, truth = stream(gap=(0.0, 2.5))
    packets = [p.replace(series={k: v for k, v in p.series.items() if k != "foe"})
               for p in packets]
    ctx, _ = score_ctx(packets, truth, tmp_path)
    t, f = ctx.metrics["ttc"], ctx.metrics["foe"]
    assert 0.45 < t["coverage_last3s"] < 0.5
    assert t["median_rel_error_last3s"] is None and t["median_rel_error_all"] is None
    assert "estimates at 47% of the times" in t["why_none"]["median_rel_error_last3s"]
    assert f["n"] == 0 and f["dx_mean_px"] is None
    assert f["why_none"].startswith("no FOE estimate in the 2.9 s after the warm-up")


class NoObstacleTruth(ExpansionTruth):
    """An expansion with nothing ahead to contact: the TTC is undefined at every time."""

    def ttc(self, t_us):
        return np.full(np.shape(t_us), np.nan)


def test_no_obstacle_scores_no_ttc_and_writes_no_nan(tmp_path):
    packets, _ = stream()
    ctx, out = score_ctx(packets, NoObstacleTruth(FOE, 4.0), tmp_path)
    t = ctx.metrics["ttc"]
    assert t["n"] == 0 and t["n_estimates"] == 390 and "no obstacle ahead" in t["why_none"]
    err = out.series["ttc_error"]
    assert len(err) == 390
    assert (err["tau_true_s"] == -1).all() and (err["rel_error"] == -1).all()
    assert ctx.metrics["foe"]["dx_mean_px"] == 0.0


def with_clusters(packets, at):
    """The packets with a ``ttc_clusters`` series: one cluster per ttc tick, centred at
    ``at(t_s)``."""
    out = []
    for p in packets:
        t = p.series["ttc"]["t"]
        x, y = at(t * 1e-6)
        cl = TTC_CLUSTERS.array(t=t, cluster=np.full(len(t), 2), x=np.broadcast_to(x, len(t)),
                                y=np.broadcast_to(y, len(t)), size_px=np.full(len(t), 6.0),
                                tau_s=np.ones(len(t)), support=np.ones(len(t)),
                                ground_ratio=np.full(len(t), -1.0))
        out.append(p.with_series("ttc_clusters", cl))
    return out


def test_misses_by_reason(tmp_path):
    """The window's lost times by reason: off the obstacle (with or without a cluster on it),
    no estimate, on it but over 20 % off; with the headline they sum to 1."""
    def moving(t_s):
        x, y = on_car(t_s)
        return np.where(t_s >= 2.5, x, 60.0), y

    m, _ = score(*stream(at=moving)[:1], ObjectTruth(4.0), tmp_path)
    miss = m["ttc"]["misses"]
    assert miss == {"no_estimate": 0.0, "off_obstacle": pytest.approx(161 / WINDOW),
                    "off_obstacle_with_a_cluster_on_it": None, "on_obstacle_over_20pct": 0.0}
    # a live cluster on the car while the reported one is off it: the choice lost those times
    packets, _ = stream(at=moving)
    m, _ = score(with_clusters(packets, on_car), ObjectTruth(4.0), tmp_path)
    miss = m["ttc"]["misses"]
    assert miss["off_obstacle_with_a_cluster_on_it"] == pytest.approx(161 / WINDOW)
    # the only cluster is the reported one: off the car, nothing on it
    packets, _ = stream(at=moving)
    m, _ = score(with_clusters(packets, moving), ObjectTruth(4.0), tmp_path)
    assert m["ttc"]["misses"]["off_obstacle_with_a_cluster_on_it"] == 0.0
    # a gap without estimates, and estimates on the car 30 % off
    m, _ = score(*stream(at=on_car, gap=(2.0, 3.0))[:1], ObjectTruth(4.0), tmp_path)
    t = m["ttc"]
    assert t["misses"]["no_estimate"] == pytest.approx(1.0 - t["coverage_last3s"])
    assert t["misses"]["no_estimate"] > 0.25
    m, _ = score(*stream(tau_factor=1.3, at=on_car)[:1], ObjectTruth(4.0), tmp_path)
    t = m["ttc"]
    assert t["misses"]["on_obstacle_over_20pct"] == 1.0 and t["misses"]["off_obstacle"] == 0.0
    for t in (m["ttc"],):
        assert t["share_on_obstacle_within_20pct"] + sum(
            v for k, v in t["misses"].items() if k != "off_obstacle_with_a_cluster_on_it") \
            == pytest.approx(1.0)
