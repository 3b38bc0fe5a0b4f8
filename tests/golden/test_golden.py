"""Golden tests: the headline FOE and TTC numbers on two short stretches of the reference drive.

The tests render each stretch (tests/golden/stretch.py: 2 s cruising, for the FOE, and the last
2 s before the obstacle, for the TTC) from three nearby starts, run both reference chains over
them and compare the medians of the metrics with tests/golden/expected.json within the
tolerances stated there. Those values change
only through ``python -m tests.golden.update --reason "..."``, which prints what changed and
records why.
"""

import json
import math

import pytest

from tests.golden import stretch

pytestmark = pytest.mark.golden


@pytest.fixture(scope="module")
def expected() -> dict:
    return json.loads(stretch.EXPECTED.read_text())


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Each stretch's events, rendered once for both flows."""
    out = tmp_path_factory.mktemp("golden")
    return out, stretch.record_all(out)


def test_expected_values_are_complete(expected):
    assert expected["reason"].strip(), "every change of the expected values says why"
    for name, (_, keys) in stretch.STRETCHES.items():
        for flow in stretch.FLOWS:
            assert set(expected["values"][name][flow]) == set(keys)
            tol = expected["tolerance"][name][flow]
            assert set(tol) == set(keys) and all(t > 0 for t in tol.values())


@pytest.mark.parametrize("name", list(stretch.STRETCHES))
@pytest.mark.parametrize("flow", list(stretch.FLOWS))
def test_headline_numbers(name, flow, recorded, expected):
    out, events = recorded
    got, runs = stretch.medians(name, flow, events, out)
    off = []
    for key, want in expected["values"][name][flow].items():
        have, tol = got[key], expected["tolerance"][name][flow][key]
        if want is None or have is None:
            if want != have:
                off.append(f"{key}: {have} (expected {want})")
        elif not math.isclose(have, want, rel_tol=0, abs_tol=tol):
            off.append(f"{key}: median {have:.4g} of {runs[key]} (expected {want:.4g} +- "
                       f"{tol:.3g})")
    assert not off, f"{name}, {flow}: " + "; ".join(off) + (
        " -- if the change is intended: python -m tests.golden.update --reason '...'")
