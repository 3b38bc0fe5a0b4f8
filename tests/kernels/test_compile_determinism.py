"""Kernels give the same bits fresh from the JIT as loaded from numba's cache.

A reduction compiled with ``fastmath={"reassoc"}`` may be vectorised differently in the two
paths, so a first run and later runs can differ in their last bits (as ``foe_map``'s estimates
did with a reassociated reduction), and a reduction loop that also stores per element runs
its vectorised or its scalar code by run-time checks of where the arrays lie, which differs
between a process that compiles and one that loads (as ``foe_fit``'s pass did with its band
terms). Each case runs in two subprocesses sharing a new cache folder: the first compiles, the
second loads.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

_READ_ESTIMATE = """
import numpy as np
from evchain.kernels import foe_map as k
rng = np.random.default_rng(3)
ny, nx = 41, 97
m = rng.normal(size=(ny, nx)) * 1e3
lo = np.zeros(ny, np.int64)
hi = np.full(ny, nx - 1, np.int64)
rowmax = m.max(axis=1)
out = [k.read_estimate(m, 0, 0, m.max(), m.min(), f, lo, hi, rowmax) for f in (0.05, 0.5)]
print([float(v).hex() for xy in out for v in xy])
"""

_FOE_FIT_SUMS = """
import numpy as np
from evchain.kernels import foe_fit as k
rng = np.random.default_rng(4)
n = 5000
x, y = rng.uniform(0, 320, n), rng.uniform(0, 240, n)
a = rng.uniform(0, 2 * np.pi, n)
nx, ny = np.cos(a), np.sin(a)
s, e = rng.uniform(0.1, 50, n), rng.uniform(0.2, 1, n)
c = k.rotation_coefficients(x, y, nx, ny, 380.0, 159.5, 119.5)
th = np.array([160.0, 120.0, 0.002, 0.003, 0.004])
lo, hi = np.array([0, 2000]), np.array([2000, n])
om = rng.normal(0, 30, (2, 3))
out = []
for rotating in (True, False):
    shared, slabs = np.zeros(19), np.zeros((2, k.NS))
    rho, u1, u2 = rng.uniform(0.8, 1.2, n), np.zeros(n), np.zeros(n)
    w = (x, y, nx, ny, s, e, *c)
    k._pass(w, lo, hi, om, 1.0, th, 10.0, 0.5, rho, rotating, shared, slabs)
    k._band_terms(w, lo, hi, om, 1.0, th, 10.0, 0.5, rho, u1, u2)
    out += [*shared, *slabs.ravel(), *u1, *u2]
print([float(v).hex() for v in out])
"""


@pytest.mark.parametrize("code", [_READ_ESTIMATE, _FOE_FIT_SUMS], ids=["foe_map", "foe_fit"])
def test_fresh_and_cached_compiles_agree(code, tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}

    def run() -> str:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              env=env, cwd=ROOT, timeout=300)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()

    fresh = run()
    assert any((tmp_path / "cache").rglob("*.nbc")), "the first run wrote no cache"
    assert run() == fresh
