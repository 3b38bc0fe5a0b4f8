"""polarity: keeps what it says, contract."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.filters.polarity import Polarity
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import random_events


@pytest.mark.parametrize("keep,sign", [("on", 1), ("off", -1), ("both", 0)])
def test_polarity(keep, sign):
    ev = random_events(2000, seed=8)
    out = check_filter(Polarity, {"keep": keep}, recut([ev], [30_000, 60_000]))
    if sign:
        assert np.all(out["p"] == sign)
        assert len(out["p"]) == np.count_nonzero(ev.p == sign) > 0
        assert np.array_equal(out["t"], ev.t[ev.p == sign])
    else:
        assert np.array_equal(out["t"], ev.t) and np.array_equal(out["p"], ev.p)
