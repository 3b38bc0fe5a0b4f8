"""The contract suite itself must catch broken filters."""

import pytest

from evchain.testing.contract import ContractError, check_filter, check_source, recut
from evchain.testing.synthetic import random_events
from tests.core import toy_filters


def stream():
    return [random_events(200, t_start=0, t_end=50_000, seed=1),
            random_events(300, t_start=50_000, t_end=120_000, seed=2)]


def test_good_filter_passes():
    out = check_filter(toy_filters.ToyFlow, {"gain": 2.0}, stream())
    assert len(out["vx"]) == 500 and (out["vx"] == 2.0).all()


def test_cut_dependent_filter_fails():
    with pytest.raises(ContractError, match="cutting the stream"):
        check_filter(toy_filters.CutDependent, {}, stream())


def test_mutating_filter_fails():
    with pytest.raises(ContractError, match="mutated its input"):
        check_filter(toy_filters.Mutator, {}, stream())


def test_recut_keeps_every_event():
    packets = recut(stream(), [7, 50_000, 50_001, 99_999])
    assert sum(len(p) for p in packets) == 500
    assert [p.t_start for p in packets] == [0, 7, 50_000, 50_001, 99_999]


def test_source_contract(tmp_path):
    got = check_source(toy_filters.ToySource, {"packets": 2}, out_dir=tmp_path)
    assert len(got) == 2
