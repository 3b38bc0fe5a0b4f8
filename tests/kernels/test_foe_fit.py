"""``foe_fit`` kernel: recovery on synthetic piecewise-planar flow, against the numpy reference,
and hard inputs (no road, all events on one line, FOE near the border, nothing at all)."""

import numpy as np
import pytest

from evchain.kernels import foe_fit as k
from evchain.kernels.records import record
from tests.naive import foe_fit as naive

A = (1 / 22.8, 1 / 40.0, 1 / 25.0)  # road K = f h / V = 22.8 s px; facades


def _run(x, y, nx, ny, s, th0, t=None, T=1e6, tau=2e5, margin=10.0, c=0.5, iters=12):
    t = np.full(len(x), T - 1.0) if t is None else t
    th = np.array(th0, np.float64)
    e, g = np.exp((t - t[0]) / tau) if len(t) else t, np.exp(-(T - (t[0] if len(t) else 0)) / tau)
    prm = record(k.FitParams, margin=margin, tolerance=c, max_iter=iters, max_step=3.0)
    ok, inl, tot = k.fit(k.FitEvents(x, y, nx, ny, s, e), 0, len(x), g, th, prm)
    return ok, th, inl, tot


@pytest.mark.parametrize("foe", [(159.5, 119.5), (140.0, 105.0), (20.0, 30.0)])
def test_recovers_foe_and_scales(foe):
    rng = np.random.default_rng(1)
    x, y, nx, ny, s = naive.planar_flow(20000, foe, A, rng, noise=0.1, outliers=0.1)
    ok, th, inl, tot = _run(x, y, nx, ny, s, (foe[0] + 8, foe[1] - 8, np.nan, np.nan, np.nan))
    assert ok and 0 < inl <= tot
    assert abs(th[0] - foe[0]) < 0.3 and abs(th[1] - foe[1]) < 0.3
    assert abs(th[2] / A[0] - 1) < 0.05


def test_matches_naive_on_random_input():
    rng = np.random.default_rng(2)
    for _ in range(5):
        foe = rng.uniform(40, 200, 2)
        x, y, nx, ny, s = naive.planar_flow(3000, foe, A, rng, noise=0.2, outliers=0.2)
        t = np.sort(rng.uniform(0, 1e6, len(x)))
        th0 = (foe[0] + rng.normal(0, 5), foe[1] + rng.normal(0, 5), np.nan, 0.03, np.nan)
        ok, th, inl, tot = _run(x, y, nx, ny, s, th0, t=t)
        ok2, th2, inl2, tot2 = naive.fit(x, y, nx, ny, s, t, 1e6, 2e5, th0, 10.0, 0.5, 12, 3.0)
        assert ok == ok2
        np.testing.assert_allclose(th, th2, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose([inl, tot], [inl2, tot2], rtol=1e-9)


def test_no_road_events_still_fits_from_facades():
    rng = np.random.default_rng(3)
    foe = (159.5, 119.5)
    x, y, nx, ny, s = naive.planar_flow(20000, foe, (0.0, A[1], A[2]), rng, noise=0.05)
    up = y < foe[1]  # only what lies above the FOE
    ok, th, _, _ = _run(x[up], y[up], nx[up], ny[up], s[up], (165, 112, np.nan, np.nan, np.nan))
    assert ok and np.isnan(th[2])
    assert abs(th[0] - foe[0]) < 0.5 and abs(th[1] - foe[1]) < 1.0


def test_hard_inputs_do_not_blow_up():
    e = np.zeros(0)
    ok, th, inl, tot = _run(e, e, e, e, e, (100, 100, np.nan, np.nan, np.nan))
    assert not ok and inl == 0 and tot == 0
    # all events on one line (one row below the FOE, one normal): the system is singular
    n = 500
    x = np.linspace(10, 300, n)
    y = np.full(n, 200.0)
    nx, ny = np.zeros(n), np.ones(n)
    s = (y - 119.5) ** 2 * A[0]
    ok, th, _, _ = _run(x, y, nx, ny, s, (159.5, 119.5, np.nan, np.nan, np.nan))
    assert np.isfinite(th[:2]).all()
    # flow exactly along an axis and events at the FOE itself
    x = np.array([159.5, 200.0, 159.5, 100.0])
    y = np.array([119.5, 119.5, 200.0, 119.5])
    nx, ny = np.array([1.0, 1.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0, 0.0])
    s = np.array([1.0, 2.0, 3.0, 4.0])
    ok, th, _, _ = _run(x, y, nx, ny, s, (159.5, 119.5, np.nan, np.nan, np.nan))
    assert np.isfinite(th[:2]).all()


def test_solve_matches_numpy():
    rng = np.random.default_rng(4)
    for _ in range(20):
        M = rng.normal(size=(5, 5)) + 5 * np.eye(5)
        b = rng.normal(size=5)
        want = np.linalg.solve(M, b)
        assert k.solve(M.copy(), b)
        np.testing.assert_allclose(b, want, rtol=1e-10, atol=1e-12)
    assert not k.solve(np.zeros((5, 5)), np.ones(5))


def test_matches_naive_on_hard_inputs():
    # events at the FOE, exactly on the margin, with dn = 0, road/facade ties (equal predicted
    # speeds), on one line, and every plane scale NaN or set: the branch-free plane choice
    # must pick what the plain version picks
    rng = np.random.default_rng(6)
    foe = (159.5, 119.5)
    x, y, nx, ny, s = naive.planar_flow(2000, foe, A, rng, noise=0.1, outliers=0.2)
    k_ = 400
    x[:k_:4], y[:k_:4] = foe  # at the FOE
    y[1:k_:4] = foe[1] + 10.0  # on the road's margin
    x[2:k_:4] = foe[0] - 10.0  # on the left facade's margin
    d = np.abs(x[3:k_:4] - foe[0])
    y[3:k_:4] = foe[1] + d  # dy = |dx|: road and facade predictions tie when a0 = a1 = a2
    nx[:50], ny[:50] = -ny[:50], nx[:50]  # some normals turned by 90 deg
    t = np.sort(rng.uniform(0, 1e6, len(x)))
    # distinct times: with all weights equal the initial weighted median sits exactly on a half
    # and the kernel's and numpy's summation orders may pick neighbouring values
    line = (np.linspace(10, 300, 200), np.full(200, 200.0), np.zeros(200), np.ones(200),
            np.full(200, 3.0))
    for th0 in [(foe[0], foe[1], 0.03, 0.03, 0.03), (foe[0], foe[1], np.nan, np.nan, np.nan),
                (foe[0] + 3, foe[1] - 2, np.nan, 0.03, np.nan)]:
        for ev, tt in [((x, y, nx, ny, s), t), (line, np.linspace(0, 9e5, 200))]:
            for iters in (1, 4):
                ok, th, inl, tot = _run(*ev, th0, t=tt, iters=iters)
                ok2, th2, inl2, tot2 = naive.fit(*ev, tt, 1e6, 2e5, th0, 10.0, 0.5, iters, 3.0)
                assert ok == ok2
                np.testing.assert_allclose(th, th2, rtol=1e-6, atol=1e-6)
                np.testing.assert_allclose([inl, tot], [inl2, tot2], rtol=1e-9)


def _sums_as_system(sm):
    A = np.zeros((5, 5))
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = sm[0], sm[1], sm[1], sm[2]
    b = np.zeros(5)
    b[:2] = sm[3], sm[4]
    for p in range(3):
        A[0, 2 + p] = A[2 + p, 0] = sm[7 + 4 * p]
        A[1, 2 + p] = A[2 + p, 1] = sm[8 + 4 * p]
        A[2 + p, 2 + p] = sm[9 + 4 * p]
        b[2 + p] = sm[10 + 4 * p]
    return A, b, sm[5], sm[6]


def test_one_pass_matches_naive_normal_equations():
    # the vectorised pass (reassociated sums) against the plain J^T W J, J^T W r on random
    # input and on the hard events of test_matches_naive_on_hard_inputs; NaN and set scales
    rng = np.random.default_rng(7)
    foe = (159.5, 119.5)
    x, y, nx, ny, s = naive.planar_flow(3000, foe, A, rng, noise=0.2, outliers=0.2)
    x[:100:4], y[:100:4] = foe
    y[1:100:4] = foe[1] + 10.0
    x[2:100:4] = foe[0] - 10.0
    y[3:100:4] = foe[1] + np.abs(x[3:100:4] - foe[0])
    e = np.exp(rng.uniform(-3, 0, len(x)))
    g = 0.7
    for th in [(foe[0], foe[1], 0.03, 0.03, 0.03), (foe[0] + 3, foe[1] - 2, np.nan, 0.03, 0.05),
               (foe[0], foe[1], 0.04, np.nan, np.nan), (foe[0], foe[1], np.nan, np.nan, np.nan)]:
        th = np.array(th)
        for i0, i1 in [(0, len(x)), (5, 5), (17, 1000)]:
            A_, b_, inl, tot = _sums_as_system(k._sums(x, y, nx, ny, s, e, i0, i1, g, th, 10.0,
                                                       0.5))
            sl = slice(i0, i1)
            A2, b2, inl2, tot2 = naive.normal_equations(x[sl], y[sl], nx[sl], ny[sl], s[sl],
                                                        e[sl] * g, th, 10.0, 0.5)
            assert np.isfinite(A_).all() and np.isfinite(b_).all()
            np.testing.assert_allclose(A_, A2, rtol=1e-10, atol=1e-12 * (1 + abs(A2).max()))
            np.testing.assert_allclose(b_, b2, rtol=1e-10, atol=1e-12 * (1 + abs(b2).max()))
            np.testing.assert_allclose([inl, tot], [inl2, tot2], rtol=1e-12, atol=1e-300)


def test_facade_scales_start_from_events_above_the_foe():
    """Road events dominate below the horizon and also lie beside the FOE: started from them,
    the facades' scales came out several times too large (a wrong local minimum the fit kept on
    the reference drive). Only events above the FOE's row start the facades."""
    foe, a = (159.5, 119.5), (1 / 22.8, 1 / 250.0, 1 / 180.0)  # far facades, as on the drive
    for seed in range(3):
        rng = np.random.default_rng(seed)
        x, y, nx, ny, s = naive.planar_flow(40000, foe, a, rng, noise=0.1)
        keep = y > foe[1] - 40  # mostly road: little of the facades above the FOE
        x, y, nx, ny, s = x[keep], y[keep], nx[keep], ny[keep], s[keep]
        for x0 in (foe[0] - 8, foe[0] + 8):
            ok, th, _, _ = _run(x, y, nx, ny, s, (x0, foe[1], np.nan, np.nan, np.nan))
            assert ok
            np.testing.assert_allclose(th[2:] / np.array(a), 1.0, atol=0.05)
            assert abs(th[0] - foe[0]) < 0.1 and abs(th[1] - foe[1]) < 0.1


def test_scales_unbiased_under_relative_speed_noise():
    """Weights and residuals relative to the predicted speed: 30 % relative noise leaves the
    facades' scales within 1.5 % (relative to the measured speed they came out 4-9 % high)."""
    foe = (159.5, 119.5)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        x, y, nx, ny, s = naive.planar_flow(20000, foe, A, rng, noise=0.3)
        ok, th, _, _ = _run(x, y, nx, ny, s, (*foe, np.nan, np.nan, np.nan))
        assert ok
        np.testing.assert_allclose(th[3:] / np.array(A[1:]), 1.0, atol=0.015)
        assert abs(th[0] - foe[0]) < 0.1 and abs(th[1] - foe[1]) < 0.1


def _obstacle_scene(foot, seed=1):
    """The reference drive's last second in miniature: the drive's facade scales, a car
    standing on the road ``foot`` rows below the FOE hides road and facades in its box, and as
    many events as the rest of the scene lie on its lower part (0.6-1 of the foot row: bumper,
    wheels)."""
    rng = np.random.default_rng(seed)
    foe, a = (159.5, 119.5), (1 / 22.8, 1 / 200.0, 1 / 170.0)
    hw = 86.0
    x, y, nx, ny, s = naive.planar_flow(20000, foe, a, rng, noise=0.1, outliers=0.1)
    seen = ~((np.abs(x - foe[0]) < hw) & (y - foe[1] > -10) & (y - foe[1] < foot))
    ev = [v[seen] for v in (x, y, nx, ny, s)]
    ob = naive.obstacle_flow(int(seen.sum()), foe, a[0], (foot, hw, 0.6 * foot), rng, noise=0.1)
    return foe, [np.concatenate([u, v]) for u, v in zip(ev, ob, strict=True)]


def _obstacle_fits(foot, c):
    foe, (x, y, nx, ny, s) = _obstacle_scene(foot)
    th = np.array((foe[0], foe[1], np.nan, np.nan, np.nan))
    for _ in range(40):  # warm-started fits in a row, as the filter runs them
        ok, _, _ = k.fit(k.FitEvents(x, y, nx, ny, s, np.ones(len(x))), 0, len(x), 1.0, th,
                         record(k.FitParams, margin=10.0, tolerance=c, max_iter=4, max_step=3.0))
        assert ok and np.isfinite(th[:2]).all()
    return th[0] - foe[0], th[1] - foe[1]


@pytest.mark.parametrize("foot", [45.0, 70.0])
def test_fronto_parallel_obstacle_does_not_pull_the_foe(foot):
    """With the filter's default Tukey constant (0.25) the obstacle's lower rows are outliers
    of the road and the FOE stays (docs/explanation/foe_ttc.md)."""
    from evchain.filters.foe_fit import FoeFit

    dx, dy = _obstacle_fits(foot, FoeFit.Params().tolerance)
    assert abs(dx) < 0.5 and abs(dy) < 0.5


def test_fronto_parallel_obstacle_pulls_the_foe_with_a_loose_tolerance():
    """Why the default is tight: with Tukey 0.5 the obstacle's rows from 2/3 of its foot row
    down fit the road, and the warm-started fits rise."""
    dx, dy = _obstacle_fits(45.0, 0.5)
    assert dy < -2.0


@pytest.mark.xfail(strict=True, reason="known: an obstacle whose foot is only 30 rows below "
                   "the FOE still pulls it at Tukey 0.25 (docs/explanation/foe_ttc.md, Limits)")
def test_nearer_the_horizon_obstacle_does_not_pull_the_foe():
    from evchain.filters.foe_fit import FoeFit

    dx, dy = _obstacle_fits(30.0, FoeFit.Params().tolerance)
    assert abs(dx) < 0.5 and abs(dy) < 0.5
