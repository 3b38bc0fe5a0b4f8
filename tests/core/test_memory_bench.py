"""The peak-memory benchmark's inputs: a stream repeated end to end, through the reference
flow chain's parameters."""

import numpy as np

from evchain.benchmarks.memory import FLOW_CHAIN, PIPELINE, WORKLOADS, chain_text, write_repeated
from evchain.core.config import load_pipeline, pipeline_from_text
from evchain.core.registry import make_registry
from evchain.io.aedat2 import read_aedat2, write_aedat2
from evchain.testing.synthetic import random_events


def test_a_recording_repeated_end_to_end(tmp_path):
    ev = random_events(50, seed=3)
    write_aedat2(tmp_path / "one.aedat", ev, chip="davis240")
    one = read_aedat2(tmp_path / "one.aedat")
    n = write_repeated(tmp_path / "x3.aedat", 0.0, 3, source=tmp_path / "one.aedat")
    three = read_aedat2(tmp_path / "x3.aedat")
    span = one.t_end - one.t_start
    assert n == len(three) == 3 * len(one)
    assert np.array_equal(three.t, np.concatenate([one.t + k * span for k in range(3)]))
    assert np.array_equal(three.x, np.tile(one.x, 3))


def test_the_chain_is_the_reference_flow_chain(tmp_path):
    write_aedat2(tmp_path / "e.aedat", random_events(10, seed=1), chip="davis240")
    spec = pipeline_from_text(chain_text(tmp_path / "e.aedat"), "m.yaml", make_registry())
    assert [s.use for s in spec.stages] == ["aedat", *FLOW_CHAIN]
    reference = load_pipeline(PIPELINE, make_registry())
    for use in FLOW_CHAIN:  # reference-lk.yaml's settings
        assert spec.stage(use).params == reference.stage(use).params
    assert "memory-flow-chain" in WORKLOADS and "memory-flow-chain" in make_registry().workloads
