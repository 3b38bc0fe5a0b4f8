"""exact_speed: the true normal speed on the estimated directions, the events it drops, the
error without flow truth, contract."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.errors import ConfigError
from evchain.filters.exact_speed import ExactSpeed
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import ExpansionTruth

G = Geometry(40, 30, f=40.0)
# flow (x - 20, y - 15) / (2 s - t): at t = 1 s it is (x - 20, y - 15) px/s; no flow after 2 s
TRUTH = ExpansionTruth((20.0, 15.0), 2.0)


def flow_packet(rows, t_end=3_000_000) -> FlowPacket:
    x, y, t, vx, vy = (np.array(c) for c in zip(*rows, strict=True))
    return FlowPacket(geometry=G, t_start=0, t_end=t_end, x=x.astype(np.uint16),
                      y=y.astype(np.uint16), t=t.astype(np.int64),
                      p=np.ones(len(x), np.int8), vx=vx.astype(np.float32),
                      vy=vy.astype(np.float32))


def run(packet: FlowPacket, truth=TRUTH) -> FlowPacket:
    f = ExactSpeed()
    f.setup(ExactSpeed.Params(), Context(geometry=G, truth=truth))
    return f.process(packet)


def test_true_normal_speed_on_the_estimated_direction():
    # at t = 1 s the true flow at (x, y) is (x - 20, y - 15) px/s
    packet = flow_packet([
        (30, 15, 1_000_000, 3.0, 0.0),      # u = (10, 0), normal (1, 0): 10 -> (10, 0)
        (24, 18, 1_000_000, 0.0, -7.0),     # u = (4, 3), normal (0, -1): -3 -> dropped
        (24, 18, 1_000_000, 6.0, 8.0),      # u = (4, 3), normal (0.6, 0.8): 4.8 -> (2.88, 3.84)
        (20, 25, 1_500_000, 1.0, 1.0),      # t = 1.5 s: u = (0, 20), normal (1, 1)/sqrt 2:
                                            # 20/sqrt 2 -> (10, 10)
        (10, 15, 1_000_000, 0.0, 5.0),      # u = (-10, 0) across the normal (0, 1): 0 -> dropped
        (30, 15, 2_500_000, 3.0, 0.0),      # after the collision: no truth -> dropped
        (30, 15, 1_000_000, 0.0, 0.0),      # no direction -> dropped
    ])
    out = run(packet)
    assert out.x.tolist() == [30, 24, 20] and out.t.tolist() == [1_000_000] * 2 + [1_500_000]
    assert np.allclose(out.vx, [10.0, 2.88, 10.0], rtol=1e-6)
    assert np.allclose(out.vy, [0.0, 3.84, 10.0], rtol=1e-6, atol=1e-6)
    assert out.vx.dtype == np.float32 and (out.t_start, out.t_end) == (0, 3_000_000)


def test_empty_packet_passes():
    empty = FlowPacket.empty(G, 0, 1000)
    out = run(empty)
    assert len(out) == 0 and (out.t_start, out.t_end) == (0, 1000)


@pytest.mark.parametrize("truth,why", [(None, "the source provides no ground truth"),
                                       (object(), "the ground truth (object) has no")])
def test_without_flow_truth_fails_at_setup(truth, why):
    with pytest.raises(ConfigError, match=r"stage 'exact_speed' needs ground truth with flow "
                                          r"\(FlowTruth\), but " + why.replace("(", r"\(")
                       .replace(")", r"\)")):
        run(FlowPacket.empty(G, 0, 1000), truth=truth)


class UniformFlow:
    """Flow truth only (no FOE, no TTC): (5, 0) px/s everywhere."""

    def flow(self, x, y, t_us):
        return np.full(np.shape(x), 5.0), np.zeros(np.shape(x))


def test_flow_truth_alone_is_enough():
    out = run(flow_packet([(3, 4, 10, 1.0, 1.0), (3, 4, 20, -1.0, 0.0)]), truth=UniformFlow())
    assert out.t.tolist() == [10] and np.allclose([out.vx[0], out.vy[0]], [2.5, 2.5])


def test_contract():
    rng = np.random.default_rng(4)
    n = 600
    x, y = rng.integers(0, 40, n), rng.integers(0, 30, n)
    t = np.sort(rng.integers(0, 2_500_000, n))
    vx, vy = rng.normal(0, 5, n), rng.normal(0, 5, n)
    packet = flow_packet(list(zip(x, y, t, vx, vy, strict=True)), t_end=2_500_000)
    out = check_filter(ExactSpeed, {}, recut([packet], [800_000, 1_900_000]), truth=TRUTH)
    kept = run(packet)
    assert 0 < len(out["t"]) == len(kept) < n
    assert np.array_equal(out["vx"], kept.vx) and np.array_equal(out["vy"], kept.vy)
