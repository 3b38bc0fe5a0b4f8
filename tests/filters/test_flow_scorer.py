"""flow_scorer: exact numbers on hand-made packets, time series, density, contract, pipelines."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.series import FLOW_DENSITY, FLOW_ERROR, DensityCounter
from evchain.errors import ConfigError
from evchain.filters.flow_scorer import FlowScorer, flow_errors, score_flow
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import expansion_stream

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data" / "dvsflow16"
G = Geometry(200, 20)


class ConstTruth:
    """u = (10, 0) px/s everywhere left of x = 100, unknown right of it; FOE at (0, 0)."""

    def flow(self, x, y, t_us):
        x = np.asarray(x, float)
        return np.where(x < 100, 10.0, np.nan), np.where(x < 100, 0.0, np.nan)

    def foe(self, t_us):
        z = np.zeros(np.shape(t_us))
        return z, z


# x, y, t, vx, vy: five flow events with known errors (see test_exact_numbers)
EVENTS = [(5, 0, 10_000, 10.0, 0.0),    # exact
          (5, 5, 20_000, 0.0, 10.0),    # perpendicular: EE 14.14, normal EE 10, 90 deg
          (5, 5, 150_000, -5.0, 0.0),   # backwards: EE 15, normal EE 15, 180 deg, invalid
          (3, 4, 160_000, 5.0, 5.0),    # 45 deg, exact normal flow: EE 7.07, normal EE 0
          (150, 5, 170_000, 1.0, 0.0)]  # no ground truth; valid direction


def packet(rows, t_start, t_end, density=None):
    x, y, t, vx, vy = (np.array(c) for c in zip(*rows, strict=True)) if rows else [[]] * 5
    p = FlowPacket(geometry=G, t_start=t_start, t_end=t_end, x=np.asarray(x, np.uint16),
                   y=np.asarray(y, np.uint16), t=np.asarray(t, np.int64),
                   p=np.ones(len(t), np.int8), vx=np.asarray(vx, np.float32),
                   vy=np.asarray(vy, np.float32))
    if density is not None:
        p = p.with_series(FLOW_DENSITY.name, FLOW_DENSITY.array(t=[density[0]], n_in=[density[1]],
                                                                n_out=[density[2]]))
    return p.validate()


def run_scorer(packets, truth=None, **params):
    f = FlowScorer()
    ctx = Context(geometry=G, truth=truth if truth is not None else ConstTruth())
    f.setup(FlowScorer.Params(**params), ctx)
    outs = [f.process(p) for p in packets]
    last = f.flush()
    return outs + ([last] if last is not None else []), ctx.metrics["flow"]


def test_exact_numbers():
    packets = [packet(EVENTS[:2], 0, 100_000, density=(100_000, 12, 2)),
               packet(EVENTS[2:], 100_000, 200_000, density=(200_000, 8, 3))]
    outs, m = run_scorer(packets)
    r2 = math.sqrt(2)
    assert m["n_flow"] == 5 and m["n_scored"] == 4 and m["n_no_ground_truth"] == 1
    assert m["aee_pxs"] == pytest.approx((0 + 10 * r2 + 15 + 5 * r2) / 4)
    assert m["ree_pct"] == pytest.approx(100 * (0 + r2 + 1.5 + r2 / 2) / 4)
    assert m["aee_normal_pxs"] == pytest.approx((0 + 10 + 15 + 0) / 4)
    assert m["ree_normal_pct"] == pytest.approx(100 * (0 + 1.5 + 0) / 3)  # u_n = 0 excluded
    assert m["aae_deg"] == pytest.approx((0 + 90 + 180 + 45) / 4)
    assert m["invalid_rate"] == pytest.approx(1 / 5)
    assert m["outliers_ree50"] == pytest.approx(3 / 4)
    assert m["outliers_ree_normal50"] == pytest.approx(1 / 3)
    assert m["outliers_ae45"] == pytest.approx(2 / 4)
    assert m["density"] == pytest.approx(5 / 20)
    assert m["n_input_events"] == 20
    # by true normal speed: the exact event (|u_n| 10) and the backwards one (10, ree 1.5) in
    # 10-20 px/s, the 45-degree one (|u_n| 7.07, exact) in 5-10; u_n = 0 is not scored
    bins = {tuple(b["normal_speed_pxs"]): b for b in m["by_normal_speed"]}
    assert bins[(5.0, 10.0)]["share"] == pytest.approx(1 / 3)
    assert bins[(5.0, 10.0)]["ree_normal_pct"] == pytest.approx(0.0, abs=1e-9)
    assert bins[(10.0, 20.0)]["share"] == pytest.approx(2 / 3)
    assert bins[(10.0, 20.0)]["ree_normal_pct"] == pytest.approx(75.0)
    assert bins[(10.0, 20.0)]["outliers_ree_normal50"] == pytest.approx(0.5)
    assert bins[(500.0, None)]["share"] == 0.0 and bins[(500.0, None)]["ree_normal_pct"] is None
    assert sum(b["adds_to_ree_normal_pct"] for b in bins.values()) == pytest.approx(
        m["ree_normal_pct"])
    assert sum(b["adds_to_outliers_ree_normal50"] for b in bins.values()) == pytest.approx(
        m["outliers_ree_normal50"])
    # pass-through: columns unchanged
    for a, b in zip(outs[:2], packets, strict=True):
        for c in FlowPacket.columns:
            np.testing.assert_array_equal(getattr(a, c), getattr(b, c))
    series = np.concatenate([o.series[FLOW_ERROR.name] for o in outs])
    assert list(series["t"]) == [100_000, 200_000]
    assert list(series["n"]) == [2, 3]
    assert series["aee_pxs"][0] == pytest.approx(10 * r2 / 2)
    assert series["aee_normal_pxs"][1] == pytest.approx(15 / 2)
    assert series["aae_deg"][1] == pytest.approx((180 + 45) / 2)
    assert series["invalid_rate"][0] == 0.0
    assert series["invalid_rate"][1] == pytest.approx(1 / 3)


def test_score_flow_matches_scorer():
    x, y, t, vx, vy = (np.array(c, float) for c in zip(*EVENTS, strict=True))
    direct = score_flow(x, y, t, vx, vy, ConstTruth())
    _, m = run_scorer([packet(EVENTS, 0, 200_000)])
    for k, v in direct.items():
        if k == "by_normal_speed":  # a list of per-bin dicts
            for a, b in zip(m[k], v, strict=True):
                assert a == {q: b[q] if b[q] is None or isinstance(b[q], list)
                             else pytest.approx(b[q]) for q in b}
        else:
            assert m[k] == pytest.approx(v), k
    assert m["density"] is None  # no flow_density series: unknown


def test_no_foe_and_nan_truth():
    class FlowOnly:
        def flow(self, x, y, t_us):
            return np.full(np.shape(x), np.nan), np.full(np.shape(x), np.nan)

    _, m = run_scorer([packet(EVENTS, 0, 200_000)], truth=FlowOnly())
    assert m["invalid_rate"] is None
    assert m["not_scored"] == "invalid_rate: the ground truth (FlowOnly) has no FOE (FoeTruth)"
    assert m["aee_pxs"] is None and m["n_scored"] == 0 and m["n_no_ground_truth"] == 5
    assert "not_scored" not in run_scorer([packet(EVENTS, 0, 200_000)])[1]   # has an FOE
    e = flow_errors([1.0], [2.0], [0.0], [0.0], [0.0], ConstTruth())  # zero flow vector
    assert np.isnan(e["ae_deg"][0]) and np.isnan(e["invalid"][0]) and e["ee"][0] == 10.0


def test_series_do_not_depend_on_cuts():
    whole = packet(EVENTS, 0, 400_000)
    ref, m_ref = run_scorer([whole])
    for cuts in ([5_000, 100_000, 100_001], [150_000, 160_000, 160_001, 300_000]):
        outs, m = run_scorer(recut([whole], cuts))
        a = np.concatenate([o.series[FLOW_ERROR.name] for o in ref])
        b = np.concatenate([o.series[FLOW_ERROR.name] for o in outs])
        np.testing.assert_array_equal(a, b)
        assert m == m_ref


def test_density_counter():
    c = DensityCounter(100)
    # a slice ending exactly at the bin end has not passed it yet ...
    assert c.add(np.array([5, 50]), np.array([50]), 100).tolist() == []
    # ... one reaching past it has: the bin is emitted with t = its end
    e1 = c.add(np.array([100]), np.array([], np.int64), 101)
    assert e1.tolist() == [(100, 2, 1)]
    c.reset()
    e1 = c.add(np.array([5, 50, 150]), np.array([50]), 101)
    assert e1.tolist() == [(100, 2, 1)]
    e2 = c.add(np.array([], np.int64), np.array([], np.int64), 200)
    assert e2.tolist() == []
    e3 = c.add(np.array([250]), np.array([250]), 260)
    assert e3.tolist() == [(200, 1, 0)]
    assert c.flush().tolist() == [(300, 1, 1)]


def test_needs_truth():
    f = FlowScorer()
    with pytest.raises(ConfigError, match="ground truth"):
        f.setup(FlowScorer.Params(), Context(geometry=G))


def test_contract(tmp_path):
    packets, truth = expansion_stream()
    out = check_filter(FlowScorer, {"bin_us": 20_000}, packets, truth=truth, out_dir=tmp_path)
    assert len(out[f"series:{FLOW_ERROR.name}"]) > 0


@pytest.mark.skipif(not (DATA / "TranslatingSquare.aedat").is_file(),
                    reason="DVSFLOW16 data not available in ../shared/data/dvsflow16")
@pytest.mark.parametrize("name", ["dvsflow16-square-plane", "dvsflow16-rotatingbar-plane"])
def test_dvsflow16_pipelines(name, tmp_path, monkeypatch):
    from evchain.core.chain import run_pipeline
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    monkeypatch.chdir(tmp_path)  # the pipelines name the data relative to their own folder
    spec = load_pipeline(ROOT / "pipelines" / f"{name}.yaml", make_registry())
    run_pipeline(spec, make_registry(), tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    m = report["metrics"]["flow"]
    assert report["status"] == "ok"
    for key in ("aee_pxs", "aee_normal_pxs", "aae_deg", "invalid_rate", "density"):
        assert key in m
    assert 0.5 < m["density"] <= 1.0
    assert m["aee_pxs"] < 2.0 and m["aae_deg"] < 6.0
    assert os.path.exists(tmp_path / "out" / "series" / "flow_error.csv")
