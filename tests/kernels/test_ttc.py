"""The ``ttc`` kernel's clustering, fusion and selection against the plain-Python reference
(tests/naive/ttc.py): random streams and parameters (with and without the camera's rotation in
the FOE entries), and hard inputs (empty packets, events on cluster borders, all clusters
dying, every slot taken, tau crossing 0, rotation only, flow near the FOE)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.core.series import FOE as FOE_SERIES
from evchain.filters.foe_map import foe_series
from evchain.filters.ttc import Ttc
from tests.naive.ttc import PX, ttc_naive

G = Geometry(96, 72, f=80.0)
FOE = (48.0, 20.0)
EXACT = ("t", "cluster")


def packet(t_start, t_end, x=(), y=(), t=(), p=(), vx=(), vy=(), foe=None):
    """A flow packet; ``foe``: list of (t, x, y) entries of its ``foe`` series, or of
    (t, x, y, wx, wy, wz, rotation) with the camera's angular velocity (deg/s)."""
    pk = FlowPacket(geometry=G, t_start=t_start, t_end=t_end, x=np.asarray(x, np.uint16),
                    y=np.asarray(y, np.uint16), t=np.asarray(t, np.int64),
                    p=np.asarray(p, np.int8), vx=np.asarray(vx, np.float32),
                    vy=np.asarray(vy, np.float32))
    if foe and len(foe[0]) == 3:
        ft, fx, fy = zip(*foe, strict=True)
        pk = pk.with_series("foe", foe_series(list(fx), list(fy), list(ft), [1.0] * len(ft)))
    elif foe:
        ft, fx, fy, wx, wy, wz, rot = zip(*foe, strict=True)
        pk = pk.with_series("foe", FOE_SERIES.array(t=ft, x=fx, y=fy, support=[1.0] * len(ft),
                                                    total=[1.0] * len(ft), wx_deg_s=wx,
                                                    wy_deg_s=wy, wz_deg_s=wz, rotation=rot))
    return pk


def rotational_flow(x, y, w):
    """The rotational flow (px/s) of G's pinhole camera turning at w (rad/s)."""
    X, Y = (np.asarray(x, float) - G.cx) / G.f, (np.asarray(y, float) - G.cy) / G.f
    return (G.f * (X * Y * w[0] - (1 + X * X) * w[1] + Y * w[2]),
            G.f * ((1 + Y * Y) * w[0] - X * Y * w[1] - X * w[2]))


def expanding(x, y, tau, rng, noise=0.02, foe=FOE):
    """Flow of points at (x, y) with time to contact ``tau`` (s): (p - foe) / tau, with
    relative noise."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    k = 1.0 + noise * rng.standard_normal((2, x.size))
    return (x - foe[0]) / tau * k[0], (y - foe[1]) / tau * k[1]


def random_stream(seed, duration_us=600_000, n_packets=8, n_blobs=5, n=1500, nan_foe=True,
                  empty=True, rotation=False):
    """Blobs below the FOE, each with its own time to contact (falling 1 s/s), some outliers;
    the FOE given per packet (jittered, now and then NaN), now and then an empty packet. With
    ``rotation`` the camera turns (a random angular velocity per packet, its flow added to
    the events, the entries carrying it with a little error, as fitted to the flow (rotation
    1) or measured (2); now and then an entry without one: rotation 0)."""
    rng = np.random.default_rng(seed)
    cx = rng.uniform(10, 86, n_blobs)
    cy = rng.uniform(28, 68, n_blobs)
    tau0 = rng.uniform(0.3, 4.0, n_blobs)
    b = rng.integers(0, n_blobs, n)
    t = np.sort(rng.integers(0, duration_us, n))
    x = np.clip(np.round(cx[b] + rng.normal(0, 3, n)), 0, G.width - 1)
    y = np.clip(np.round(cy[b] + rng.normal(0, 3, n)), 0, G.height - 1)
    tau = np.maximum(tau0[b] - t * 1e-6, 0.05)
    vx, vy = expanding(x, y, tau, rng)
    out = rng.random(n) < 0.1
    vx[out] = rng.normal(0, 80, out.sum())
    vy[out] = rng.normal(0, 80, out.sum())
    p = rng.choice([-1, 1], n)
    cuts = np.linspace(0, duration_us, n_packets + 1).astype(np.int64)
    omega = rng.normal(0, 0.15, (n_packets, 3)) * rotation
    packets = []
    for k in range(n_packets):
        lo, hi = np.searchsorted(t, cuts[k]), np.searchsorted(t, cuts[k + 1])
        if rotation:
            ru, rv = rotational_flow(x[lo:hi], y[lo:hi], omega[k])
            vx[lo:hi] += ru
            vy[lo:hi] += rv
        if empty and rng.random() < 0.2:
            lo = hi  # an empty packet (its events are dropped)
        entries = [(int(cuts[k]) + int(rng.integers(0, 5000)),
                    FOE[0] + rng.normal(0, 1), FOE[1] + rng.normal(0, 1))]
        if rotation:
            w = np.degrees(omega[k] * (1 + rng.normal(0, 0.05, 3)))
            # rotation 1: fitted to the flow, 2: measured (the baseline then integrates the
            # angle), 0: none
            entries = [(*entries[0], *w, int(rng.choice([0, 1, 2], p=[0.15, 0.45, 0.4])))]
        if nan_foe and rng.random() < 0.3:
            entries.append((entries[0][0] + 1, np.nan, np.nan, *entries[0][3:]))
        packets.append(packet(int(cuts[k]), int(cuts[k + 1]), x[lo:hi], y[lo:hi], t[lo:hi],
                              p[lo:hi], vx[lo:hi], vy[lo:hi], entries))
    return packets


def compare(packets, **params):
    """Kernel (through the filter) and reference give the same rows; returns them."""
    q = Ttc.Params(**{**PX, **params})
    f = Ttc()
    f.setup(q, Context(geometry=G))
    outs = [f.process(pk) for pk in packets]
    got = {name: np.concatenate([o.series[name] for o in outs])
           for name in ("ttc", "ttc_clusters")}
    why = {}
    want_ttc, want_cl = ttc_naive(packets, f.params_on(G), G.width, G.height, why, G.f, G.cx,
                                  G.cy)
    from evchain.kernels.ttc import no_ttc_counts, slotless_events

    if f._state is not None:
        assert {**no_ttc_counts(f._state), "no_slot": slotless_events(f._state)} == why
    for name, want in (("ttc", want_ttc), ("ttc_clusters", want_cl)):
        have = got[name]
        assert len(have) == len(want), (name, len(have), len(want))
        if not want:
            continue
        for j, field in enumerate(have.dtype.names):
            col = np.array([row[j] for row in want])
            if field in EXACT:
                np.testing.assert_array_equal(have[field], col.astype(np.int64), err_msg=field)
            else:
                np.testing.assert_allclose(have[field], col, rtol=1e-9, atol=1e-12,
                                           err_msg=field)
    return got["ttc"], got["ttc_clusters"]


@pytest.mark.parametrize("seed", range(4))
def test_random_streams_match_reference(seed):
    ttc, cl = compare(random_stream(seed), baseline_px=0, min_samples=3)
    assert len(ttc) > 20 and len(np.unique(cl["cluster"])) >= 3


@pytest.mark.parametrize("seed", range(4))
def test_random_rotating_streams_match_reference(seed):
    """The FOE entries carry the camera's angular velocity: each event's tau is that of its
    flow less the rotational flow (from the flow and from the baseline)."""
    for baseline, width in ((0, 0), (4, 0), (4, 1)):
        ttc, cl = compare(random_stream(seed, rotation=True), baseline_px=baseline,
                          baseline_width_px=width, min_samples=3)
    assert len(ttc) > 10


def test_rotation_only():
    """Flow that is the camera's rotation alone, the entries carrying it exactly: nothing is
    left to expand, so no event has a tau and there is no cluster; without the rotation in the
    entries the same flow gives clusters."""
    rng = np.random.default_rng(5)
    n = 2000
    t = np.sort(rng.integers(0, 400_000, n))
    x, y = rng.integers(0, G.width, n), rng.integers(36, G.height, n)
    w = np.array([0.3, -0.2, 0.1])
    vx, vy = rotational_flow(x, y, w)
    wd = np.degrees(w)
    cuts = np.linspace(0, 400_000, 5).astype(np.int64)

    def stream(flag):
        out = []
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            k = slice(np.searchsorted(t, a), np.searchsorted(t, b))
            out.append(packet(int(a), int(b), x[k], y[k], t[k], np.ones(n)[k], vx[k], vy[k],
                              [(int(a), *FOE, *wd, flag)]))
        return out

    ttc, cl = compare(stream(1), baseline_px=0, min_samples=3)
    assert len(cl) == 0 and len(ttc) == 0
    ttc, cl = compare(stream(0), baseline_px=0, min_samples=3)
    assert len(cl) > 0


def test_rotation_near_the_foe_and_zero():
    """Flow near the FOE (within min_distance and just outside) with a rotation, and entries
    with zero rotation but rotation 1: as the reference, finite."""
    rng = np.random.default_rng(6)
    n = 600
    t = np.sort(rng.integers(0, 200_000, n))
    x = np.clip(np.round(FOE[0] + rng.normal(0, 6, n)), 0, G.width - 1)
    y = np.clip(np.round(FOE[1] + rng.normal(0, 6, n)), 0, G.height - 1)
    vx, vy = expanding(x, y, 1.5, rng, noise=0.05)
    ru, rv = rotational_flow(x, y, (0.05, 0.02, 0.0))
    for w, flag in (((0.0, 0.0, 0.0), 1), (np.degrees((0.05, 0.02, 0.0)), 1)):
        pk = [packet(0, 100_000, x[:n // 2], y[:n // 2], t[:n // 2], np.ones(n // 2),
                     vx[:n // 2] + ru[:n // 2], vy[:n // 2] + rv[:n // 2],
                     [(0, *FOE, *w, flag)]),
              packet(100_000, 200_000, x[n // 2:], y[n // 2:], t[n // 2:], np.ones(n // 2),
                     vx[n // 2:] + ru[n // 2:], vy[n // 2:] + rv[n // 2:])]
        for baseline, width in ((0, 0), (3, 0), (3, 1)):
            ttc, _ = compare(pk, baseline_px=baseline, baseline_width_px=width,
                             min_samples=3)
            assert np.isfinite(ttc["tau_s"]).all()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), select=st.sampled_from(["nearest_foe", "support"]),
       ground=st.booleans(), corridor=st.sampled_from([None, 1.0, 3.0]),
       hold=st.booleans(), fallback=st.booleans(),
       baseline=st.sampled_from([(0, 0), (4, 0), (4, 1), (4, 2), (1, 1)]),
       max_clusters=st.sampled_from([1, 2, 3, 8, 32]), min_samples=st.sampled_from([1, 3, 8]),
       size=st.sampled_from([(3.0, 5.0, 1.0), (6.0, 15.0, 4.0), (10.0, 10.0, 0.0)]),
       activity=st.sampled_from([(30.0, 1.0), (100.0, 2.0), (400.0, 5.0)]),
       ring=st.sampled_from([4, 16, 256]), period=st.sampled_from([3_000, 10_000, 25_000]),
       spread=st.sampled_from([None, 0.02, 0.1, 0.5]),
       tau_bounds=st.sampled_from([(0.02, 20_000.0), (0.5, 20_000.0), (0.02, 100.0)]))
def test_random_parameters_match_reference(seed, select, ground, corridor, hold, fallback,
                                           baseline, max_clusters, min_samples, size, activity,
                                           ring, period, spread, tau_bounds):
    compare(random_stream(seed, n=900), select=select, ground_test=ground,
            ground_min_events=40, corridor_half_width_h=corridor, select_hold=hold,
            ground_fallback=fallback, baseline_px=baseline[0], baseline_width_px=baseline[1],
            max_clusters=max_clusters,
            min_samples=min_samples, cluster_size_px=size[0], max_cluster_size_px=size[1],
            join_margin_px=size[2], activity_tau_ms=activity[0], min_activity=activity[1],
            samples_per_cluster=ring, estimate_every_us=period, select_min_activity=2.0,
            max_rel_spread=spread, min_tau_s=tau_bounds[0], max_speed_pxs=tau_bounds[1])


def test_empty_packets():
    """Packets without events (before, between and after the events; with and without FOE
    entries) still tick: the clusters decay and their predictions fall 1 s/s."""
    stream = random_stream(7, duration_us=300_000, n_packets=4, empty=False)
    packets = ([packet(0, 50_000), packet(50_000, 50_000, foe=[(50_000, *FOE)])]
               + [packet(pk.t_start + 50_000, pk.t_end + 50_000, pk.x, pk.y, pk.t + 50_000, pk.p,
                         pk.vx, pk.vy, [(pk.t_start + 50_000, *FOE)]) for pk in stream]
               + [packet(350_000, 360_000), packet(360_000, 600_000)])
    ttc, cl = compare(packets, baseline_px=0, min_samples=3, activity_tau_ms=300.0)
    late = ttc[ttc["t"] >= 350_000]
    assert len(late) > 3 and not (ttc["t"] < 50_000).any()


def test_events_on_cluster_borders():
    """An event exactly ``size + join_margin`` (inf-norm) from a cluster's centre joins it and
    grows it; one 1 px farther starts a new cluster."""
    rng = np.random.default_rng(0)
    x0, y0 = 40, 50
    xs = [x0] * 6 + [x0 + 6, x0 - 6, x0 + 3, x0 + 20, x0 + 20, x0 + 20]
    ys = [y0] * 6 + [y0 + 2, y0 - 6, y0 + 6, y0, y0 + 1, y0]
    t = np.arange(len(xs)) * 1000 + 1000
    vx, vy = expanding(xs, ys, 2.0, rng, noise=0.0)
    pk = packet(0, 40_000, xs, ys, t, [1] * len(xs), vx, vy, [(0, *FOE)])
    params = dict(baseline_px=0, min_samples=1, cluster_size_px=4.0, join_margin_px=2.0,
                  max_cluster_size_px=30.0, estimate_every_us=20_000, min_activity=0.5)
    ttc, cl = compare([pk], **params)
    assert len(np.unique(cl["cluster"])) == 2
    # one px farther than the widened square: a second cluster already at x0 + 7
    xs[6] = x0 + 7
    vx, vy = expanding(xs, ys, 2.0, rng, noise=0.0)
    _, cl = compare([packet(0, 40_000, xs, ys, t, [1] * len(xs), vx, vy, [(0, *FOE)])],
                    **params)
    assert len(np.unique(cl["cluster"])) == 3


def test_all_clusters_die_and_new_ones_start():
    """After a silence longer than the activity decay every cluster is removed; the next
    events start new clusters (new ids) in the freed slots."""
    first = random_stream(3, duration_us=200_000, n_packets=2, empty=False)
    again = random_stream(4, duration_us=200_000, n_packets=2, empty=False)
    quiet = [packet(200_000, 700_000, foe=[(200_000, *FOE)])]
    later = [packet(pk.t_start + 700_000, pk.t_end + 700_000, pk.x, pk.y, pk.t + 700_000, pk.p,
                    pk.vx, pk.vy, [(pk.t_start + 700_000, *FOE)]) for pk in again]
    ttc, cl = compare(first + quiet + later, baseline_px=0, min_samples=3,
                      activity_tau_ms=50.0)
    gap = cl[(cl["t"] > 450_000) & (cl["t"] < 700_000)]
    assert len(gap) == 0
    before = set(cl["cluster"][cl["t"] < 200_000])
    after = set(cl["cluster"][cl["t"] > 700_000])
    assert before and after and min(after) > max(before)


def test_every_slot_taken():
    """More places than cluster slots: new clusters take only decayed slots, the events that
    find every slot held by a live cluster start none (and are counted)."""
    ttc, cl = compare(random_stream(11, n_blobs=8, n=2000), baseline_px=0, min_samples=2,
                      max_clusters=3, cluster_size_px=3.0, max_cluster_size_px=4.0,
                      join_margin_px=0.0)
    per_tick = np.unique(cl["t"], return_counts=True)[1]
    assert per_tick.max() <= 3 and cl["cluster"].max() > 10  # ids far beyond the slots


def test_a_live_cluster_keeps_its_slot():
    """With every slot held by a live cluster an event elsewhere starts no cluster: the
    clusters keep their ids and samples (before, the least active one was replaced)."""
    rng = np.random.default_rng(3)
    t = np.arange(0, 200_000, 2_000)
    a = dict(x=np.full(t.size, 30), y=np.full(t.size, 50))
    b = dict(x=np.full(t.size, 70), y=np.full(t.size, 60))
    xs = np.concatenate([a["x"], b["x"], [50]])
    ys = np.concatenate([a["y"], b["y"], [40]])
    ts = np.concatenate([t, t + 1000, [150_001]])
    order = np.argsort(ts, kind="stable")
    xs, ys, ts = xs[order], ys[order], ts[order]
    vx, vy = expanding(xs, ys, 2.0, rng, noise=0.0)
    pk = packet(0, 200_000, xs, ys, ts, [1] * ts.size, vx, vy, [(0, *FOE)])
    f = Ttc()
    params = dict(baseline_px=0, max_clusters=2, min_samples=2, min_activity=0.5)
    f.setup(Ttc.Params(**PX, **params), Context(geometry=G))
    f.process(pk)
    from evchain.kernels.ttc import slotless_events

    assert slotless_events(f._state) == 1
    ttc, cl = compare([pk], **params)
    assert set(cl["cluster"]) == {0, 1}


def test_tau_crossing_zero():
    """A cluster whose predicted tau reaches 0 (an object at contact) is dropped although it
    is still active; a later event there starts a new cluster."""
    rng = np.random.default_rng(5)
    n = 60
    x = rng.integers(40, 46, n)
    y = rng.integers(50, 56, n)
    t = np.sort(rng.integers(0, 30_000, n))
    vx, vy = expanding(x, y, 0.08 - t * 1e-6, rng, noise=0.0)
    packets = [packet(0, 30_000, x, y, t, [1] * n, vx, vy, [(0, *FOE)]),
               packet(30_000, 150_000, foe=[(30_000, *FOE)]),
               packet(150_000, 200_000, x[:5], y[:5], t[:5] + 150_000, [1] * 5,
                      *expanding(x[:5], y[:5], 1.0, rng, noise=0.0))]
    ttc, cl = compare(packets, baseline_px=0, min_samples=3, activity_tau_ms=5000.0,
                      estimate_every_us=5_000, min_tau_s=0.01)
    first = cl["cluster"][0]
    rows = cl[cl["cluster"] == first]
    assert (rows["tau_s"] > 0).all() and rows["t"].max() < 150_000
    assert rows["tau_s"].min() < 0.01
    assert (cl["cluster"][cl["t"] > 150_000] != first).all()


def _medians(values):
    """The kernel's median of ``values`` (on a copy) and the reference's."""
    from evchain.kernels.ttc import median as median_kernel
    from tests.naive.ttc import median as median_naive

    a = np.array(values, np.float64)
    return median_kernel(a.copy(), len(a)), median_naive(list(a))


@pytest.mark.parametrize("seed", range(6))
def test_median_matches_reference_on_random_input(seed):
    """The selection median (used per cluster and tick) is exactly the sorted median, for odd
    and even counts, whatever the slice it works on."""
    rng = np.random.default_rng(seed)
    for n in range(1, 300, 7):
        got, want = _medians(rng.normal(1.0, 2.0, n))
        assert got == want, n
    buf = rng.uniform(0, 5, 256)  # only buf[:n] counts; the rest is left as it was
    tail = buf[40:].copy()
    from evchain.kernels.ttc import median as median_kernel

    assert median_kernel(buf, 40) == np.median(buf[:40]) and (buf[40:] == tail).all()


@pytest.mark.parametrize("values", [
    [3.0], [2.0, 1.0], [1.0, 1.0, 1.0, 1.0], [5.0, 5.0, 1.0, 5.0], [0.0, -0.0, 1.0],
    list(range(256)), list(range(256, 0, -1)), [7.0] * 255 + [1.0], [1.0, 2.0] * 128,
    [1e300, -1e300, 0.5, np.inf, -np.inf, 2.0], [1.0 + k * 1e-16 for k in range(33)]])
def test_median_matches_reference_on_hard_input(values):
    """Single values, pairs, ties, sorted and reversed rings, near-equal values and
    infinities."""
    got, want = _medians(values)
    assert got == want


def test_a_cluster_is_reported_and_ground_tested_by_its_agreeing_samples():
    """Samples of a car (tau 2 s) and of the road below it (tau 1 s) in one square: the
    cluster's position is the median of the samples within 20 % of its measurement, not its
    square's centre, and so is its ground ratio (their median tau * dy over K) where at least
    ``min_samples`` agree; with none within, the position stays as it was, and with fewer than
    ``min_samples`` the ground ratio stays."""
    from typing import NamedTuple

    from evchain.kernels.ttc import CLUSTER_STATE, _agreeing_samples

    class Prm(NamedTuple):
        max_age_us: float
        min_samples: int

    cl = np.zeros(1, CLUSTER_STATE)
    cl[0]["n_samples"] = 6
    cl[0]["mx"] = cl[0]["my"] = cl[0]["rho"] = np.nan
    T = 1_000_000.0
    K = 10.0
    ST = np.full((1, 8), T)
    SV = np.array([[2.0, 2.3, 1.75, 1.0, 1.1, 0.9, 2.0, 2.0]])    # the last two are unused
    SK = np.array([[7.0, 8.0, 6.0, 10.0, 10.5, 9.5, 0.0, 0.0]])   # tau * dy: car 0.7 K, road K
    SX = np.array([[100.0, 104.0, 101.0, 90.0, 95.0, 99.0, 0.0, 0.0]])
    SY = np.array([[50.0, 52.0, 51.0, 90.0, 91.0, 92.0, 0.0, 0.0]])
    buf = np.empty(24)                                             # three rings
    _agreeing_samples(cl[0], 0, ST, SV, SK, SX, SY, T, K, 2.0, buf, Prm(500_000.0, 3))
    assert (cl[0]["mx"], cl[0]["my"], cl[0]["rho"]) == (101.0, 51.0, 0.7)
    # samples moved forward to T at -1 s/s: 0.3 s old, 2.0 and 2.3 s are 1.7 and 2.0 s now,
    # within 20 % of 1.9; 1.75 s is 1.45 s, not. Two agree: fewer than min_samples 3, so the
    # ground ratio stays; with min_samples 2 it is theirs
    ST[0, :3] = T - 300_000.0
    _agreeing_samples(cl[0], 0, ST, SV, SK, SX, SY, T, K, 1.9, buf, Prm(500_000.0, 3))
    assert (cl[0]["mx"], cl[0]["my"], cl[0]["rho"]) == (102.0, 51.0, 0.7)
    _agreeing_samples(cl[0], 0, ST, SV, SK, SX, SY, T, K, 1.9, buf, Prm(500_000.0, 2))
    assert cl[0]["rho"] == 0.75
    # the road's samples agree with a road measurement: a road ratio
    _agreeing_samples(cl[0], 0, ST, SV, SK, SX, SY, T, K, 1.0, buf, Prm(500_000.0, 3))
    assert (cl[0]["mx"], cl[0]["my"], cl[0]["rho"]) == (95.0, 91.0, 1.0)
    # too old, or none agreeing: the position and the ratio stay
    _agreeing_samples(cl[0], 0, ST, SV, SK, SX, SY, T, K, 2.0, buf, Prm(100_000.0, 3))
    _agreeing_samples(cl[0], 0, ST, SV, SK, SX, SY, T, K, 5.0, buf, Prm(500_000.0, 3))
    assert (cl[0]["mx"], cl[0]["my"], cl[0]["rho"]) == (95.0, 91.0, 1.0)
