"""Every pipeline shipped in pipelines/ validates against the installed filters."""

from pathlib import Path

import pytest

from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry

PIPELINES = sorted((Path(__file__).resolve().parents[2] / "pipelines").glob("*.yaml"))


def test_there_are_pipelines():
    assert PIPELINES, "pipelines/ holds no YAML"


@pytest.mark.parametrize("path", PIPELINES, ids=[p.name for p in PIPELINES])
def test_pipeline_validates(path):
    spec = load_pipeline(path, make_registry())
    assert spec.stages[0].cls.is_source()
