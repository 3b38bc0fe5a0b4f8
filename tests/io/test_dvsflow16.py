"""DVSFLOW16 ground truth from .mat files: layout, validity window, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat

from evchain.errors import DataError
from evchain.io.dvsflow16 import DVSFLOW16Truth

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dvsflow16"


def write_gt(path, vx, vy, ts=(1000, 2000)):
    savemat(str(path), {"vxGT": vx, "vyGT": vy, "ts": np.array([ts], np.int32)})
    return path


def test_layout_and_window(tmp_path):
    vx = np.zeros((4, 5))
    vy = np.zeros((4, 5))
    vx[0, 2] = 7.0  # file row 0 = jAER y 0 = bottom row = evchain y 3
    vy[0, 2] = 3.0  # up in jAER = -y in evchain
    vx[3, 4] = -1.0
    tr = DVSFLOW16Truth(write_gt(tmp_path / "gt.mat", vx, vy), height=4, width=5)
    assert tr.flow(2, 3, 1500) == (7.0, -3.0)
    assert tr.flow(4, 0, 1000) == (-1.0, -0.0)
    gx, gy = tr.flow(np.array([2, 2, 2, 2, 9, 1]), np.array([3, 3, 3, 0, 0, 1]),
                     np.array([999, 1999, 2000, 1500, 1500, 1500]))
    # before the window, inside, at its (exclusive) end, no truth (zeros), outside, zeros
    np.testing.assert_array_equal(np.isnan(gx), [True, False, True, True, True, True])
    np.testing.assert_array_equal(gy[1], -3.0)
    up = DVSFLOW16Truth(tmp_path / "gt.mat", y_up=True)
    assert up.flow(2, 0, 1500) == (7.0, 3.0)


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="not found"):
        DVSFLOW16Truth(tmp_path / "nope.mat")


def test_garbage_file(tmp_path):
    bad = tmp_path / "bad.mat"
    bad.write_bytes(b"this is not a MATLAB file at all" * 10)
    with pytest.raises(DataError, match="bad.mat"):
        DVSFLOW16Truth(bad)


def test_missing_variables(tmp_path):
    p = tmp_path / "x.mat"
    savemat(str(p), {"vxGT": np.zeros((2, 2))})
    with pytest.raises(DataError, match="missing"):
        DVSFLOW16Truth(p)


def test_shape_and_window_checks(tmp_path):
    with pytest.raises(DataError, match="one shape"):
        DVSFLOW16Truth(write_gt(tmp_path / "a.mat", np.zeros((2, 3)), np.zeros((3, 2))))
    with pytest.raises(DataError, match="sensor"):
        DVSFLOW16Truth(write_gt(tmp_path / "b.mat", np.zeros((2, 3)), np.zeros((2, 3))),
                       height=180, width=240)
    with pytest.raises(DataError, match="ts must be"):
        DVSFLOW16Truth(write_gt(tmp_path / "c.mat", np.zeros((2, 3)), np.zeros((2, 3)),
                                ts=(5, 1)))


@pytest.mark.skipif(not (DATA / "gtTranslatingSquare.mat").is_file(),
                    reason="DVSFLOW16 data not available in ../shared/data/dvsflow16")
def test_square_file_matches_the_square():
    """At 2.5 s the square spans jAER x 119..159, y 79..119: in evchain coordinates its right
    edge moves +x and its top edge (evchain y = 179 - 119 = 60) moves up (-y), 20 px/s."""
    tr = DVSFLOW16Truth(DATA / "gtTranslatingSquare.mat", 180, 240)
    assert tr.flow(159, 100, 2_500_000) == (20.0, 0.0)
    assert tr.flow(130, 60, 2_500_000) == (0.0, -20.0)
    vx, vy = tr.flow(130, 90, 2_500_000)  # inside the square: no truth
    assert np.isnan(vx) and np.isnan(vy)
    assert np.isnan(tr.flow(159, 100, 2_550_000)[0])
    bar = DVSFLOW16Truth(DATA / "gtRotatingBar.mat", 180, 240)
    vx, vy = bar.flow(np.arange(240), np.full(240, 90), np.full(240, 50e6))
    assert np.nanmax(np.hypot(vx, vy)) == pytest.approx(10.47, abs=0.01)
