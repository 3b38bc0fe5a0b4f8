"""The contract suite itself must catch broken filters."""

import pytest

from evchain.core.series import FOE
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


def test_declared_series_pass():
    out = check_filter(toy_filters.ToyFoe, {}, stream())
    assert out["series:foe"].dtype == FOE.dtype and len(out["series:foe"]) == 12


@pytest.mark.parametrize("broken, pattern", [
    ("silent", r"toy_foe: declares it adds the series \['foe'\], but its output carries none"),
    ("dtype", r"toy_foe: series 'foe' has fields \(t, x, y\)"),
    ("undeclared", r"toy_foe: its output carries the series 'count', which it does not declare"),
])
def test_series_declaration_broken(broken, pattern):
    with pytest.raises(ContractError, match=pattern):
        check_filter(toy_filters.ToyFoe, {"broken": broken}, stream())


def test_input_must_carry_needed_series():
    with pytest.raises(ValueError, match=r"toy_foe_reader needs the series \['foe'\]"):
        check_filter(toy_filters.ToyFoeReader, {}, stream())
    with_foe = [p.with_series("foe", FOE.array(t=[p.t_start])) for p in stream()]
    out = check_filter(toy_filters.ToyFoeReader, {}, with_foe)  # passed through: no addition
    assert len(out["series:foe"]) == 2
    odd = [p.with_series("foe", toy_filters.COUNT.array(t=[p.t_start])) for p in stream()]
    with pytest.raises(ValueError, match=r"the input's series 'foe' has fields \(t, n\)"):
        check_filter(toy_filters.ToyFoeReader, {}, odd)
