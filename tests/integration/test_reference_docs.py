"""docs/reference/ is generated (`evchain docs`) and must match the code."""

from pathlib import Path

from evchain.core.registry import make_registry
from evchain.core.schema import filters_markdown, hooks_markdown

REFERENCE = Path(__file__).resolve().parents[2] / "docs" / "reference"


def test_filter_reference_is_up_to_date():
    assert (REFERENCE / "filters.md").read_text() == filters_markdown(make_registry()), \
        "docs/reference/filters.md is stale: run `evchain docs`"


def test_hook_reference_is_up_to_date():
    assert (REFERENCE / "hooks.md").read_text() == hooks_markdown(), \
        "docs/reference/hooks.md is stale: run `evchain docs`"
