"""Every sweep in pipelines/sweeps loads and every one of its variations validates."""

from pathlib import Path

import pytest

from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry
from evchain.sweep import load_sweep

SWEEPS = sorted((Path(__file__).resolve().parents[2] / "pipelines" / "sweeps").glob("*.yaml"))


@pytest.mark.parametrize("path", SWEEPS, ids=[p.name for p in SWEEPS])
def test_sweep_validates(path):
    sweep = load_sweep(path)
    registry = make_registry()
    assert len(sweep.variations) >= 2
    for v in sweep.variations:
        load_pipeline(sweep.base, registry, v.overrides)
