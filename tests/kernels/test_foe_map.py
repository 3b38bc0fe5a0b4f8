"""The O(rows) foe_map kernel against the brute-force O(pixels) reference."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.filters.foe_map import FoeMap
from tests.naive.foe_map import brute_map, cells, foe_naive, region_mask


def random_flow(n, g, seed, hard=False, duration_us=40_000):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, duration_us, n)).astype(np.int64)
    x = rng.integers(0, g.width, n)
    y = rng.integers(0, g.height, n)
    vx = rng.normal(0, 100, n)
    vy = rng.normal(0, 100, n)
    if hard:  # flow along the axes, zero flow, tiny flow, integer-valued directions
        k = rng.integers(0, 5, n)
        vx[k == 0] = 0.0
        vy[k == 1] = 0.0
        vx[k == 2] = vy[k == 2] = 0.0
        vx[k == 3] = np.round(vx[k == 3] / 50) * 50
        vy[k == 3] = np.round(vy[k == 3] / 50) * 50
        vx[k == 4] *= 1e-30
    return FlowPacket(geometry=g, t_start=0, t_end=duration_us, x=x.astype(np.uint16),
                      y=y.astype(np.uint16), t=t, p=np.ones(n, np.int8),
                      vx=vx.astype(np.float32), vy=vy.astype(np.float32))


CASES = [  # geometry, region radius, refine_fraction, max_angle_deg, other params
    (Geometry(40, 30), None, 0.0, None, {}),
    (Geometry(40, 30), 11.0, 0.05, None, {}),
    (Geometry(33, 21, cx=5.0, cy=18.0), 9.5, 0.0, None, {}),   # disc clipped by the border
    (Geometry(40, 30), 14.0, 0.02, 70.0, {}),                   # angular gating on
    (Geometry(40, 30), 11.0, 0.05, None, {"speed_weight_pxs": 20.0}),
    (Geometry(41, 31), None, 0.0, None, {"cell_px": 2}),         # partial last cells
    (Geometry(33, 21, cx=5.0, cy=18.0), 9.5, 0.05, 70.0,
     {"cell_px": 3, "speed_weight_pxs": 5.0}),
]


@pytest.mark.parametrize("case", range(len(CASES)))
@pytest.mark.parametrize("hard", [False, True])
def test_kernel_equals_brute_force(case, hard):
    g, radius, refine, gate, other = CASES[case]
    check_against_brute_force(random_flow(500, g, seed=case + 10 * hard, hard=hard), g, radius,
                              refine, gate, other)


def border_flow(n, g, radius, seed):
    """Flow whose boundary lines pass at distance radius + d from A's centre, d in
    {-0.6, -0.3, -1e-7, 0, 1e-7, 0.3, 0.6, 2.5} px (the kernel's classification and span use a
    disc 0.5 px wider than A): tangent lines, lines just missing or just cutting A."""
    rng = np.random.default_rng(seed)
    c = np.array([g.cx, g.cy])
    pts = np.stack([rng.integers(0, g.width, 20 * n), rng.integers(0, g.height, 20 * n)], 1)
    pts = pts[np.hypot(*(pts - c).T) > radius + 3.0][:n]
    d = radius + rng.choice([-0.6, -0.3, -1e-7, 0.0, 1e-7, 0.3, 0.6, 2.5], len(pts))
    rel = pts - c
    dist = np.hypot(*rel.T)
    theta = np.arctan2(rel[:, 1], rel[:, 0]) + rng.choice([-1, 1], len(pts)) * np.arccos(d / dist)
    v = rng.choice([-1, 1], len(pts))[:, None] * rng.uniform(1, 200, (len(pts), 1)) * np.stack(
        [np.cos(theta), np.sin(theta)], 1)
    m = len(pts)
    t = np.sort(rng.integers(0, 40_000, m)).astype(np.int64)
    return FlowPacket(geometry=g, t_start=0, t_end=40_000, x=pts[:, 0].astype(np.uint16),
                      y=pts[:, 1].astype(np.uint16), t=t, p=np.ones(m, np.int8),
                      vx=v[:, 0].astype(np.float32), vy=v[:, 1].astype(np.float32))


@pytest.mark.parametrize("g, radius", [
    (Geometry(40, 30, cx=20.0, cy=15.0), 5.0),     # cells exactly on A's circle
    (Geometry(40, 30), 11.0),
    (Geometry(33, 21, cx=5.0, cy=18.0), 9.5),     # clipped by the border
])
def test_lines_near_the_border_of_a(g, radius):
    """(p - c).v / |v| = R + d: the votes that hold all of A, none or part, near the limit."""
    check_against_brute_force(border_flow(400, g, radius, seed=3), g, radius, 0.0, None, {})


def check_against_brute_force(packet, g, radius, refine, gate, other):
    """The filter's estimates and (without gating) its whole map equal the brute force's."""
    other = {"speed_weight_pxs": 0.0, **other}  # unweighted unless the case says otherwise
    # the kernel's reads, not the noise test on them (random flow has no FOE); radius None:
    # the whole sensor, the filter's 0
    params = FoeMap.Params(tau_ms=15.0, region_radius_px=radius or 0.0, estimate_every_us=4000,
                           refine_fraction=refine, max_angle_deg=gate, significance=None,
                           **other)
    f = FoeMap()
    f.setup(params, Context())
    got = f.process(packet).series["foe"]
    ref = foe_naive(packet, 15.0, radius, 4000, refine, max_angle_deg=gate, **other)
    assert len(got) == len(ref) > 0
    assert np.array_equal(got["t"], ref[:, 0].astype(np.int64))
    np.testing.assert_allclose(got["x"], ref[:, 1], atol=1e-6)
    np.testing.assert_allclose(got["y"], ref[:, 2], atol=1e-6)
    np.testing.assert_allclose(got["support"], ref[:, 3], rtol=1e-9)
    if gate is None:  # the whole map at the end of the packet, cell by cell
        vx, vy = packet.vx.astype(np.float64), packet.vy.astype(np.float64)
        accepted = vx * vx + vy * vy > 0
        s0 = other.get("speed_weight_pxs")
        vote_w = s0 / (s0 + np.hypot(vx, vy)) if s0 else None
        gc, rc, xs, ys = cells(packet, radius, other.get("cell_px", 1))
        want = brute_map(xs, ys, packet.t, vx, vy, accepted, packet.t_end, 15000.0,
                         region_mask(gc, rc), vote_w)
        g, radius = gc, rc
        m = f.map_now(packet.t_end)
        x0, y0 = f.origin
        sub = want[y0:y0 + m.shape[0], x0:x0 + m.shape[1]]
        assert np.array_equal(np.isnan(m), np.isnan(sub))
        assert np.all(np.isnan(want[region_mask(g, radius) == 0]))
        np.testing.assert_allclose(m[~np.isnan(m)], sub[~np.isnan(sub)], rtol=1e-9,
                                   atol=1e-9 * np.nanmax(sub))


def test_renormalisation_keeps_map_exact():
    """Long gaps force many renormalisations (t - t_ref > 40 tau): still equal to brute force."""
    g = Geometry(24, 18)
    packet = random_flow(300, g, seed=5, duration_us=40_000)
    packet = packet.replace(t=packet.t * 50, t_end=2_000_000)  # 1 ms tau, ~2 s span
    f = FoeMap()
    f.setup(FoeMap.Params(tau_ms=1.0, region_radius_px=0, estimate_every_us=100_000,
                          refine_fraction=0.0, speed_weight_pxs=0, significance=None),
            Context())
    got = f.process(packet).series["foe"]
    ref = foe_naive(packet, 1.0, None, 100_000, 0.0)
    assert len(got) == len(ref) > 0
    np.testing.assert_allclose(got["x"], ref[:, 1], atol=1e-6)
    np.testing.assert_allclose(got["support"], ref[:, 3], rtol=1e-6)


@pytest.mark.parametrize("case", range(len(CASES)))
@pytest.mark.parametrize("hard", [False, True])
def test_pruned_reads_equal_full_reads(case, hard):
    """Reads recompute only the rows that can reach the threshold, the maximum or the minimum;
    the estimates equal, bit for bit, reads that recompute every row (forced by invalidating
    the per-row state before each read). Many reads, long decay gaps (renormalisation) and
    empty packets included."""
    g, radius, refine, gate, other = CASES[case]
    packet = random_flow(800, g, seed=100 + case + 10 * hard, hard=hard)
    packet = packet.replace(t=packet.t * 25, t_end=packet.t_end * 25)  # 1 s, tau 15 ms
    params = FoeMap.Params(tau_ms=15.0, region_radius_px=radius or 0.0, estimate_every_us=1000,
                           refine_fraction=refine, max_angle_deg=gate, significance=None,
                           **other)
    cuts = list(range(1000, packet.t_end, 1000))  # one read per packet
    from evchain.kernels.foe_map import forget_row_bounds
    from evchain.testing.contract import recut

    packets = recut([packet], cuts)
    pruned, full = FoeMap(), FoeMap()
    pruned.setup(params, Context())
    full.setup(params, Context())
    got, want = [], []
    for p in packets:
        got.append(pruned.process(p).series["foe"])
        if full._geometry is not None:
            forget_row_bounds(full._state)
        want.append(full.process(p).series["foe"])
    got, want = np.concatenate(got), np.concatenate(want)
    assert len(got) == len(want) > 100
    for name in want.dtype.names:
        assert np.array_equal(got[name], want[name]), name


@pytest.mark.parametrize("radius", [None, 9.5])
def test_refresh_equals_materialize_with_negative_values(radius):
    """The read's row pass (prefix sums four rows at a time, extrema over integer keys of the
    float bits) equals materialize bit for bit, also for negative and zero map values."""
    from evchain.filters.foe_map import region_cells
    from evchain.kernels import foe_map as k

    g = Geometry(33, 21, cx=15.0, cy=12.0)
    x0, y0, lo, hi, clo, chi = region_cells(g, radius)
    ny, nx = len(lo), len(clo)
    rng = np.random.default_rng(7)
    diffR = rng.normal(size=(ny, nx + 1))
    diffR[:, ::3] = 0.0
    for r in range(ny):  # the kernel never writes left of a row's first cell
        diffR[r, :max(lo[r] - x0, 0)] = 0.0
    constR, diffC, constC = rng.normal(size=ny + 1), rng.normal(size=(ny + 1, nx)), \
        rng.normal(size=nx + 1)
    want = np.empty((ny, nx))
    rowmax = np.empty(ny)
    best, worst = k.materialize(diffR, constR, diffC, constC, lo, hi, x0, -0.5, want, rowmax)
    rst = np.zeros((ny, 6))
    got = np.full((ny, nx), np.nan)
    rowv = np.stack([constR, np.zeros(ny + 1), np.zeros(ny + 1)])
    b2, w2 = k.refresh(diffR, rowv, diffC, constC, lo, hi, x0, -0.5, 1.0, rst, got, 0.05)
    assert worst < 0 < best
    assert (b2, w2) == (best, worst)
    inside = ~np.isnan(want)
    assert np.array_equal(got[inside], want[inside])
    ok = hi >= lo
    assert np.array_equal(rst[ok, k.ROW_MAX], rowmax[ok])
    assert np.array_equal(rst[ok, k.ROW_MIN], np.nanmin(want[ok], axis=1))


@pytest.mark.parametrize("refine", [0.0, 0.05, 0.5])
@pytest.mark.parametrize("kind", ["random", "plateau", "flat", "one_cell", "negative", "two_tops"])
def test_read_estimate_equals_naive(refine, kind):
    """The read's refined centroid (row sums in four interleaved lanes) against the naive
    estimate on random maps and hard ones: a wide plateau, a constant map (max = min), one
    maximal cell, negative values, two separate maximal cells; region A a clipped disc."""
    from evchain.filters.foe_map import region_cells
    from evchain.kernels import foe_map as k
    from tests.naive.foe_map import estimate

    g = Geometry(37, 23, cx=20.0, cy=9.0)
    radius = 12.5
    x0, y0, lo, hi, clo, chi = region_cells(g, radius)
    ny, nx = len(lo), len(clo)
    rng = np.random.default_rng(11)
    m = rng.normal(size=(ny, nx)) * 1e3
    if kind == "plateau":
        m = np.minimum(m, 800.0)
    elif kind == "flat":
        m[:] = 2.5
    elif kind == "one_cell":
        m[:] = 1.0
        m[ny // 2, nx // 2] = 3.0
    elif kind == "negative":
        m = -np.abs(m) - 5.0
    elif kind == "two_tops":
        m[:] = 0.0
        m[1, lo[1] - x0] = m[ny - 2, hi[ny - 2] - x0] = 7.0
    for r in range(ny):  # NaN outside A, as the map buffer
        m[r, :max(lo[r] - x0, 0)] = np.nan
        m[r, hi[r] - x0 + 1:] = np.nan
    full = np.full(g.shape, np.nan)
    full[y0:y0 + ny, x0:x0 + nx] = m
    want_x, want_y, best = estimate(full, refine)
    worst = float(np.nanmin(m))
    rowmax = np.where(hi >= lo, np.nanmax(np.where(np.isnan(m), -np.inf, m), axis=1), -np.inf)
    got_x, got_y = k.read_estimate(m, x0, y0, best, worst, refine, lo, hi, rowmax)
    assert np.isfinite(got_x) and np.isfinite(got_y)
    np.testing.assert_allclose([got_x, got_y], [want_x, want_y], rtol=0, atol=1e-9)
