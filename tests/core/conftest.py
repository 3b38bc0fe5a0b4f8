import pytest

from evchain.core.registry import make_registry
from tests.core import toy_filters


@pytest.fixture
def registry():
    return make_registry(discover=False, plugins=(toy_filters,))
