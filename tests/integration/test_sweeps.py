"""Every sweep in pipelines/sweeps loads and every run it would make validates."""

from pathlib import Path

import pytest

from evchain.core.registry import make_registry
from evchain.sweep import load_sweep, validate_sweep

SWEEPS = sorted((Path(__file__).resolve().parents[2] / "pipelines" / "sweeps").glob("*.yaml"))


@pytest.mark.parametrize("path", SWEEPS, ids=[p.name for p in SWEEPS])
def test_sweep_validates(path):
    sweep = load_sweep(path)
    assert len(sweep.runs()) >= 2
    assert validate_sweep(sweep, make_registry()) >= len(sweep.runs())
