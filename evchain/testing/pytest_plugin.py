"""pytest plugin (entry point ``pytest11``): the filter contract as fixtures.

In a plugin's tests::

    def test_my_filter_contract(filter_contract):
        from evchain.testing.synthetic import random_events
        filter_contract.check_filter(MyFilter, {"window_us": 1000}, [random_events(500)])
"""

from __future__ import annotations

import pytest

from evchain.testing import contract


class _Contract:
    def __init__(self, out_dir):
        self.out_dir = out_dir

    def check_filter(self, cls, params, packets, truth=None, seed=0):
        return contract.check_filter(cls, params, packets, truth=truth, out_dir=self.out_dir,
                                     seed=seed)

    def check_source(self, cls, params, seed=0, max_packets=50):
        return contract.check_source(cls, params, out_dir=self.out_dir, seed=seed,
                                     max_packets=max_packets)


@pytest.fixture
def filter_contract(tmp_path):
    """Contract checks writing any outputs into the test's ``tmp_path``."""
    return _Contract(tmp_path)

