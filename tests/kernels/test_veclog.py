"""The vectorised logarithm ``log_pass`` against ``np.log`` (libm) and exact decimal logs."""

from decimal import Decimal, getcontext

import numpy as np

from evchain.kernels.veclog import log_pass


def _log(x):
    out = np.full_like(x, 7.0)
    log_pass(x, out, x.size)
    return out


def _ulps(a, ref):
    return np.abs(a - ref) / np.spacing(np.abs(ref))


def _random_inputs():
    rng = np.random.default_rng(3)
    mags = np.exp(rng.uniform(-708, 709, 200_000))
    # random bit patterns of positive normal numbers (every exponent, every mantissa)
    bits = rng.integers(0x0010000000000000, 0x7FF0000000000000, 200_000, dtype=np.int64)
    near1 = 1.0 + rng.uniform(-1e-3, 1e-3, 100_000)
    frames = rng.uniform(0, 255, 100_000).astype(np.float32).astype(np.float64) + 1e-3
    return np.concatenate([mags, bits.view(np.float64), near1, frames])


def _hard_normals():
    r2, rh = np.sqrt(2.0), np.sqrt(0.5)
    pow2 = 2.0 ** np.arange(-1022, 1024)
    near = [1.0, np.nextafter(1.0, 2), np.nextafter(1.0, 0), r2, np.nextafter(r2, 0),
            np.nextafter(r2, 2), rh, np.nextafter(rh, 0), np.nextafter(rh, 1),
            np.finfo(np.float64).tiny, np.finfo(np.float64).max, np.e, 10.0, 1e-3]
    return np.concatenate([pow2, np.nextafter(pow2, 0), np.nextafter(pow2, np.inf), near])


def test_log_pass_within_one_ulp_of_libm():
    x = np.concatenate([_random_inputs(), _hard_normals()])
    got = _log(x)
    ref = np.log(x)
    assert np.all(np.isfinite(got))
    assert _ulps(got, ref).max() <= 1.0
    assert np.mean(got == ref) > 0.9


def test_log_pass_exact_where_expected():
    got = _log(np.array([1.0, 2.0, 0.5, 1024.0]))
    assert got[0] == 0.0 and not np.signbit(got[0])
    assert np.array_equal(got[1:], np.log([2.0, 0.5, 1024.0]))


def test_log_pass_true_error_below_one_ulp():
    """Against exact (40-digit) decimal logs, on the inputs deviating most from libm."""
    x = np.concatenate([_random_inputs(), _hard_normals()])
    got = _log(x)
    worst = np.argsort(_ulps(got, np.log(x)))[-300:]
    getcontext().prec = 40
    for i in worst:
        exact = Decimal(float(x[i])).ln()
        err = abs(Decimal(float(got[i])) - exact) / Decimal(float(np.spacing(abs(got[i]))))
        assert err < 1, (x[i], float(err))


def test_log_pass_non_normal_inputs_as_libm():
    x = np.array([0.0, -0.0, 5e-324, 1e-310, np.nextafter(2.0 ** -1022, 0), np.inf, -np.inf,
                  np.nan, -1.0, -2.0 ** -1030, 3.0])
    with np.errstate(all="ignore"):
        ref = np.log(x)
    got = _log(x)
    assert np.array_equal(got, ref, equal_nan=True)


def test_log_pass_only_first_n():
    x = np.array([2.0, 0.0, 4.0])
    out = np.array([9.0, 9.0, 9.0])
    log_pass(x, out, 1)
    assert out[0] == np.log(2.0) and out[1] == 9.0 and out[2] == 9.0
