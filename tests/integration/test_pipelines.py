"""Every pipeline shipped in pipelines/ validates against the installed filters."""

from pathlib import Path

import pytest

from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry

PIPELINES = sorted((Path(__file__).resolve().parents[2] / "pipelines").glob("*.yaml"))


def test_there_are_pipelines():
    assert PIPELINES, "pipelines/ holds no YAML"


SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


@pytest.mark.parametrize("path", PIPELINES, ids=[p.name for p in PIPELINES])
def test_pipeline_validates(path):
    if "shared/data/" in path.read_text() and not SHARED.is_dir():
        pytest.skip(f"{path.name} reads data from {SHARED}, which is not here")
    spec = load_pipeline(path, make_registry())
    assert spec.stages[0].cls.is_source()
    for stage in spec.stages:  # input files are absolute and exist (checked at validation)
        for key in stage.cls.input_paths:
            value = getattr(stage.params, key)
            assert value is None or Path(value).is_absolute() and Path(value).exists()


def test_exact_speed_pipeline_is_reference_lk_with_the_oracle():
    """reference-lk-exact-speed.yaml differs from reference-lk.yaml only by exact_speed right
    after lk_flow, so that its errors compare with reference-lk's."""
    root = Path(__file__).resolve().parents[2] / "pipelines"
    registry = make_registry()
    lk = load_pipeline(root / "reference-lk.yaml", registry).resolved()
    oracle = load_pipeline(root / "reference-lk-exact-speed.yaml", registry).resolved()
    uses = [s["use"] for s in oracle["chain"]]
    assert uses[uses.index("lk_flow") + 1] == "exact_speed"
    assert [s for s in oracle["chain"] if s["use"] != "exact_speed"] == lk["chain"]
    assert oracle["seed"] == lk["seed"]
