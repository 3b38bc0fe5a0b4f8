"""foe_ttc_scorer: exact metrics on constructed estimates, pictures, contract."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry, series_array
from evchain.filters.foe_map import FoeMap, foe_series
from evchain.filters.foe_ttc_scorer import FoeTtcScorer, foe_angle_deg
from evchain.filters.ttc import TTC_DTYPE, Ttc
from evchain.testing.contract import check_filter
from evchain.testing.synthetic import ExpansionTruth, expansion_stream
from tests.naive.foe_map import expansion_packets

G = Geometry(128, 96, f=100.0)
FOE = (60.0, 40.0)


def stream(dx=0.0, dy=0.0, tau_factor=1.0, t_collision=4.0, gap=None):
    """Empty flow packets of 100 ms carrying a foe estimate (true + offset) and a ttc estimate
    (true * factor) every 10 ms; ``gap`` = (t0, t1) in s without ttc estimates."""
    out = []
    for k in range(int(t_collision * 10) - 1):
        t0 = k * 100_000
        t = np.arange(t0, t0 + 100_000, 10_000, dtype=np.int64)
        tau = (t_collision - t * 1e-6) * tau_factor
        keep = np.ones(len(t), bool) if gap is None else ~((t >= gap[0] * 1e6)
                                                          & (t < gap[1] * 1e6))
        ttc = series_array(TTC_DTYPE, t=t[keep], tau_s=tau[keep], cluster=np.ones(keep.sum()),
                           x=np.full(keep.sum(), 60.0), y=np.full(keep.sum(), 60.0),
                           support=np.ones(keep.sum()))
        p = FlowPacket.empty(G, t0, t0 + 100_000)
        p = p.with_series("foe", foe_series(np.full(len(t), FOE[0] + dx),
                                            np.full(len(t), FOE[1] + dy), t, np.ones(len(t))))
        out.append(p.with_series("ttc", ttc))
    return out, ExpansionTruth(FOE, t_collision)


def score(packets, truth, tmp_path, **params):
    ctx = Context(out_dir=tmp_path, truth=truth)
    f = FoeTtcScorer()
    f.setup(FoeTtcScorer.Params(**{"plots": False, **params}), ctx)
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


def test_without_truth_passes_through(tmp_path):
    packets, _ = stream()
    m, out = score(packets, None, tmp_path)
    assert m == {} and len(out.series["foe_error"]) == len(out.series["foe"])
    assert np.isnan(out.series["foe_error"]["dx"]).all()


def test_whole_chain_writes_pictures(tmp_path):
    truth = ExpansionTruth(FOE, 1.6)
    packets = expansion_packets(foe=FOE, tau_s=1.6, n=60_000, geometry=G,
                                duration_us=1_500_000, n_packets=15, tau_shrinks=True,
                                normal_only=True)
    ctx = Context(out_dir=tmp_path, truth=truth)
    chain = [FoeMap(), Ttc(), FoeTtcScorer()]
    for f in chain:  # random points with exact flow, no moving edges: ttc's tau from the flow
        f.setup(f.Params(**({"baseline_px": 0} if isinstance(f, Ttc) else {})), ctx)
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
