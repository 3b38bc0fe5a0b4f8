"""Ground truth as protocols: who implements what, who declares what, and the one clear error
when a stage lacks the truth it needs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.io import savemat

from evchain import EventPacket, Filter, FlowPacket, Geometry
from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.filter import Context
from evchain.core.registry import make_registry
from evchain.core.truth import (
    PROTOCOLS,
    DepthTruth,
    FlowTruth,
    FoeTruth,
    ObjectTruth,
    RotationTruth,
    TtcTruth,
    describe,
)
from evchain.errors import ConfigError, FilterError
from evchain.filters.flow_scorer import FlowScorer
from evchain.filters.scene_events import SceneEvents
from evchain.io.dvsflow16 import DVSFLOW16Truth
from evchain.sim.bar import Bar, BarTruth
from evchain.sim.drive import Scene
from evchain.sim.truth import SceneTruth
from evchain.testing.contract import ContractError, check_filter, check_source
from evchain.testing.synthetic import ExpansionTruth, expansion_stream, random_events

REGISTRY = make_registry()
SCORERS = sorted(n for n, i in REGISTRY.filters.items() if i.cls.needs_truth)
G = Geometry(40, 30, f=40.0)


def implemented(truth) -> list[type]:
    return [p for p in PROTOCOLS if isinstance(truth, p)]


def test_providers_implement_their_protocols(tmp_path):
    scene = Scene.from_params(width=40, height=30, supersample=1, start_m=200.0, duration_s=0.1)
    assert implemented(SceneTruth(scene)) == list(PROTOCOLS)
    assert implemented(ExpansionTruth((20.0, 15.0), 2.0)) == [FlowTruth, FoeTruth,
                                                              RotationTruth, TtcTruth,
                                                              DepthTruth]
    assert implemented(BarTruth(Bar(width=40, height=4))) == [FlowTruth]
    path = tmp_path / "gt.mat"
    savemat(str(path), {"vxGT": np.ones((3, 4)), "vyGT": np.zeros((3, 4)),
                        "ts": np.array([[0, 1000]], np.int32)})
    assert implemented(DVSFLOW16Truth(path)) == [FlowTruth]
    assert implemented(object()) == [] and implemented(None) == []

    class IdsOnly:            # object_id without obstacle_ids is no ObjectTruth
        def object_id(self, x, y, t_us):
            return np.zeros(np.shape(x), np.int64)

    assert implemented(IdsOnly()) == []
    IdsOnly.obstacle_ids = np.array([3])
    assert implemented(IdsOnly()) == [ObjectTruth]


def test_sources_declare_what_they_provide():
    # bar, scene and aedat run the same check in the contract suite (test_contract_all)
    scene = Scene.from_params(width=40, height=30, supersample=1, start_m=200.0, duration_s=0.1)
    assert list(SceneEvents.provides_truth) == implemented(SceneTruth(scene))
    sources = sorted(n for n, i in REGISTRY.filters.items() if i.cls.provides_truth)
    assert {"bar", "scene", "scene_events"} <= set(sources)


def test_a_source_that_misdeclares_fails_the_contract(tmp_path):
    class Liar(Filter):
        """Declares flow truth, sets none."""

        name = "liar"
        produces = EventPacket
        provides_truth = (FlowTruth,)

        def setup(self, params, context):
            context.geometry = G
            super().setup(params, context)

        def packets(self):
            yield random_events(10, G, 0, 1000, seed=1)

    with pytest.raises(ContractError, match=r"liar: provides_truth declares \[flow"):
        check_source(Liar, {}, out_dir=tmp_path)


def test_a_filter_that_reads_undeclared_truth_fails_the_contract():
    class Peeker(Filter):
        """An 'algorithm' that reads the true flow: a leak of the answer."""

        name = "peeker"
        consumes = FlowPacket
        produces = FlowPacket

        def process(self, packet):
            self.context.truth.flow(packet.x, packet.y, packet.t)
            return packet

    packets, truth = expansion_stream()
    with pytest.raises(ContractError, match="peeker: reads context.truth.flow but declares"):
        check_filter(Peeker, {}, packets, truth=truth)
    Peeker.uses_truth = (FlowTruth,)      # declared: allowed
    check_filter(Peeker, {}, packets, truth=truth)


@pytest.mark.parametrize("name", SCORERS)
@pytest.mark.parametrize("truth", [None, object()], ids=["no truth", "unrelated truth"])
def test_scorer_without_the_truth_it_needs_fails_at_setup(name, truth):
    cls = REGISTRY.get(name)
    f = cls()
    f.id = "my_scorer"
    with pytest.raises(ConfigError) as err:
        f.setup(cls.Params(), Context(geometry=G, truth=truth))
    msg = str(err.value)
    assert f"stage 'my_scorer' ({name}) needs ground truth with {describe(cls.needs_truth)}" in msg
    assert ("the source provides no ground truth" if truth is None
            else "the ground truth (object) has no") in msg
    assert "sources that provide it: " in msg and "scene" in msg
    if name == "flow_scorer":
        assert msg.endswith("or give the parameter ground_truth: path/to/gt.mat (DVSFLOW16)")


def test_scorers_declare_their_truth():
    assert REGISTRY.get("flow_scorer").needs_truth == (FlowTruth,)
    assert REGISTRY.get("flow_scorer").uses_truth == (FoeTruth, ObjectTruth, TtcTruth)
    assert REGISTRY.get("foe_ttc_scorer").needs_truth == (FoeTruth, TtcTruth)
    assert REGISTRY.get("foe_ttc_scorer").uses_truth == (ObjectTruth, RotationTruth)


def test_algorithm_filters_declare_no_truth():
    algorithms = ["emulator", "lk_flow", "plane_flow", "foe_map", "foe_fit", "ttc"]
    for name in algorithms:
        cls = REGISTRY.get(name)
        assert not (cls.needs_truth or cls.uses_truth), name


def test_missing_truth_stops_a_pipeline_at_setup(registry, tmp_path):
    text = ("name: x\nchain:\n  - use: toy_source\n  - use: toy_flow\n"
            "  - use: flow_scorer\n    id: score\n")
    spec = pipeline_from_text(text, "x.yaml", registry)
    with pytest.raises(FilterError) as err:
        run_pipeline(spec, registry, tmp_path)
    msg = str(err.value)
    assert msg.startswith("filter 'score' (flow_scorer) failed in setup: stage 'score' "
                          "(flow_scorer) needs ground truth with flow (FlowTruth), but the "
                          "source provides no ground truth; sources that provide it: ")
    assert "scene_events" in msg


def test_flow_truth_from_a_file_and_what_it_cannot_score(tmp_path):
    """flow_scorer's ground_truth parameter gives flow truth without a source's; with no FOE
    the invalid rate is not scored, and the metrics say so."""
    vx = np.full((G.height, G.width), 5.0)
    path = tmp_path / "gt.mat"
    savemat(str(path), {"vxGT": vx, "vyGT": np.zeros_like(vx),
                        "ts": np.array([[0, 100_000]], np.int32)})
    f = FlowScorer()
    ctx = Context(geometry=G)
    f.setup(FlowScorer.Params(ground_truth=str(path)), ctx)
    p = random_events(50, G, 0, 50_000, seed=4)
    n = len(p)
    f.process(FlowPacket.from_events(p, np.arange(n), np.full(n, 5.0), np.zeros(n)))
    f.flush()
    m = ctx.metrics["flow"]
    assert m["aee_pxs"] == 0.0 and m["invalid_rate"] is None
    assert m["not_scored"] == ("invalid_rate: the ground truth (DVSFLOW16Truth) has no FOE "
                               "(FoeTruth)")
