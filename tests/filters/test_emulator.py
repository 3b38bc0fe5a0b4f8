"""The emulator filter: its correctness list (timing, tie rule, ordering, cuts, noise, mismatch)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evchain.core.filter import Context
from evchain.core.packets import EventPacket, FramePacket, Geometry
from evchain.errors import DataError
from evchain.filters.emulator import THESIS8BIT_UNIT, Emulator
from evchain.testing.contract import check_filter


def packets_of(frames, times, per=4):
    n, h, w = frames.shape
    g = Geometry(w, h)
    out = []
    for i in range(0, n, per):
        j = min(i + per, n)
        t_end = int(times[j]) if j < n else int(times[-1]) + 1
        out.append(FramePacket(geometry=g, t_start=int(times[i]), t_end=t_end,
                               frames=frames[i:j], t=times[i:j]))
    return out


def run(frames, times, seed=0, per=4, **params):
    f = Emulator()
    f.record_float_times = True
    f.setup(Emulator.Params(**params), Context(seed=seed))
    outs = [f.process(p) for p in packets_of(frames, times, per)]
    outs.append(f.flush())
    for a, b in zip(outs[:-1], outs[1:], strict=True):
        assert a.t_end == b.t_start
    ev = EventPacket.concat(outs).validate()
    return ev, np.concatenate(f.float_times) if f.float_times else np.zeros(0), f


def log_ramp(k_levels, c=0.2, eps=1e-3, n=21, i0=0.3, shape=(3, 4)):
    """Frames where pixel (1, 2) ramps linearly in log by k_levels thresholds (+ others static)."""
    times = np.arange(n, dtype=np.int64) * 1000
    L = np.log(i0 + eps) + np.linspace(0.0, k_levels * c, n)
    frames = np.full((n, *shape), i0, np.float32)
    frames[:, 1, 2] = np.exp(L) - eps
    return frames, times


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_static_scene_gives_no_events(interpolation):
    rng = np.random.default_rng(0)
    frame = rng.random((6, 8)).astype(np.float32)
    frame[0, 0] = 0.0
    frames = np.repeat(frame[None], 10, axis=0)
    ev, _, _ = run(frames, np.arange(10, dtype=np.int64) * 500, interpolation=interpolation,
                   mismatch_sigma=0.05)
    assert len(ev) == 0


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
@pytest.mark.parametrize("k", [1, 3, 7])
def test_ramp_of_k_thresholds_gives_k_events_at_analytic_times(k, interpolation):
    c = 0.2
    frames, times = log_ramp(k, c)
    ev, tf, _ = run(frames, times, interpolation=interpolation, threshold_on=c,
                    threshold_off=c)
    assert len(ev) == k
    assert (ev.p == 1).all() and (ev.x == 2).all() and (ev.y == 1).all()
    analytic = np.arange(1, k + 1) / k * 20_000.0     # L linear in t over 20 ms
    # event time = where L reaches level - tie_tolerance (1e-6): 0.1 us early at this slope
    np.testing.assert_allclose(tf, analytic - 1e-6 / (k * c / 20_000.0), atol=1e-3)
    np.testing.assert_array_equal(ev.t, np.floor(analytic + 0.5))
    # and down again: exactly k OFF events back to the start level (tie rule)
    down = np.concatenate([frames, frames[::-1][1:]])
    t2 = np.arange(len(down), dtype=np.int64) * 1000
    ev2, _, _ = run(down, t2, interpolation=interpolation, threshold_on=c, threshold_off=c)
    assert (ev2.p == 1).sum() == k and (ev2.p == -1).sum() == k


def test_on_off_symmetry():
    rng = np.random.default_rng(1)
    eps = 1e-3
    L = rng.normal(-1.0, 0.6, (12, 5, 6))
    up = (np.exp(L) - eps).clip(0).astype(np.float32)
    down = (np.exp(-2.0 - L) - eps).clip(0).astype(np.float32)   # L mirrored about -1
    times = np.arange(12, dtype=np.int64) * 1000
    for interp in ("linear", "cubic"):
        a, ta, _ = run(up, times, interpolation=interp, threshold_on=0.25, threshold_off=0.25)
        b, tb, _ = run(down, times, interpolation=interp, threshold_on=0.25,
                       threshold_off=0.25)
        assert len(a) > 20 and len(a) == len(b)
        oa = np.lexsort((ta, a.x, a.y))
        ob = np.lexsort((tb, b.x, b.y))
        np.testing.assert_array_equal(a.x[oa], b.x[ob])
        np.testing.assert_array_equal(a.p[oa], -b.p[ob])
        np.testing.assert_allclose(ta[oa], tb[ob], atol=0.02)   # float32 input rounding


def test_mismatch_statistics_match_sigma():
    frames = np.full((2, 120, 160), 0.5, np.float32)
    _, _, f = run(frames, np.array([0, 1000]), mismatch_sigma=0.021, threshold_on=0.3,
                  threshold_off=0.2)
    on, off = f.thresholds
    for th, c in ((on, 0.3), (off, 0.2)):
        rel = th / c
        assert abs(rel.mean() - 1) < 0.001
        assert abs(rel.std() - 0.021) < 0.001
    assert abs(np.corrcoef(on.ravel(), off.ravel())[0, 1]) < 0.02   # independent draws
    _, _, g = run(frames, np.array([0, 1000]), mismatch_sigma=0.5)
    assert g.thresholds[0].min() > 0          # clipped at a positive floor
    assert g.thresholds[0].min() == pytest.approx(0.2 * 0.01)


def test_same_seed_same_events_other_seed_differs():
    rng = np.random.default_rng(2)
    frames = np.exp(rng.normal(-1, 0.5, (10, 6, 8))).astype(np.float32)
    times = np.arange(10, dtype=np.int64) * 1000
    kw = dict(mismatch_sigma=0.05, noise_rate_hz=200.0, threshold_on=0.2, threshold_off=0.2)
    a, _, _ = run(frames, times, seed=5, **kw)
    b, _, _ = run(frames, times, seed=5, **kw)
    c, _, _ = run(frames, times, seed=6, **kw)
    for n in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(a, n), getattr(b, n))
    assert len(a) != len(c) or not np.array_equal(a.t, c.t)


def test_noise_rate():
    frames = np.full((11, 40, 50), 0.5, np.float32)
    times = np.arange(11, dtype=np.int64) * 10_000          # 0.1 s
    ev, _, _ = run(frames, times, noise_rate_hz=5.0)
    expected = 5.0 * 2000 * 0.1
    assert abs(len(ev) - expected) < 5 * math.sqrt(expected)
    assert abs((ev.p > 0).mean() - 0.5) < 0.1


def test_thesis8bit_mapping():
    # grey 10 -> 200 on the 8-bit scale: Lg = 255 ln(1+g)/ln 256
    g0, g1 = 10.0, 200.0
    lg = 255 * (math.log(1 + g1) - math.log(1 + g0)) / math.log(256)
    frames = np.linspace(g0 / 255, g1 / 255, 30).astype(np.float32)[:, None, None] * \
        np.ones((1, 2, 2), np.float32)
    times = np.arange(30, dtype=np.int64) * 1000
    ev, _, f = run(frames, times, log_mapping="thesis8bit", threshold_on=20, threshold_off=20)
    assert len(ev) == 4 * int(lg // 20)
    assert f.natural_parameters()[0] == pytest.approx(20 * math.log(256) / 255)
    assert THESIS8BIT_UNIT * 20 == pytest.approx(0.4349, abs=1e-4)


def test_refractory_drops_but_moves_reference():
    frames, times = log_ramp(6)            # 6 events 3.33 ms apart
    ev, _, _ = run(frames, times, refractory_us=5000.0)
    assert len(ev) == 3                     # every other one survives
    assert np.all(np.diff(ev.t) >= 5000)


def test_cap_carries_over():
    frames = np.array([0.01, 0.01] + [1.0] * 6, np.float32)[:, None, None] * \
        np.ones((1, 1, 1), np.float32)
    times = np.arange(8, dtype=np.int64) * 1000
    full, _, _ = run(frames, times, interpolation="linear")
    capped, _, _ = run(frames, times, interpolation="linear", max_events_per_interval=5)
    assert len(full) == len(capped) == int((math.log(1.001) - math.log(0.011)) // 0.2)
    # 22 crossings: 5 in the jump's interval, the rest carried over at the next frames
    assert list(np.bincount(capped.t // 1000)) == [0, 5, 5, 5, 5, 2]
    assert (capped.t[5:] % 1000 == 0).all()


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_contract(interpolation):
    rng = np.random.default_rng(4)
    frames = np.exp(rng.normal(-1, 0.7, (16, 5, 6))).astype(np.float32)
    times = np.cumsum(rng.integers(100, 900, 16)).astype(np.int64)
    ref = check_filter(Emulator, {"interpolation": interpolation, "noise_rate_hz": 100.0,
                                  "mismatch_sigma": 0.03}, packets_of(frames, times))
    assert len(ref["t"]) > 20


def bad_packet(frames, times, g=None):
    g = g or Geometry(frames.shape[2], frames.shape[1])
    return FramePacket(geometry=g, t_start=int(times[0]), t_end=int(times[-1]) + 1,
                       frames=frames, t=times)


@pytest.mark.parametrize("bad", ["nan_first", "nan_later", "negative", "inf", "shape",
                                 "decreasing", "decreasing_across"])
def test_bad_input_gives_clear_error(bad):
    frames = np.full((4, 3, 5), 0.5, np.float32)
    times = np.array([0, 1000, 2000, 3000], np.int64)
    f = Emulator()
    f.setup(Emulator.Params(), Context())
    pat = {"nan_first": "not finite", "nan_later": "not finite", "inf": "not finite",
           "negative": "negative", "shape": "shape", "decreasing": "increase",
           "decreasing_across": "increase"}[bad]
    with pytest.raises(DataError, match=pat) as info:
        if bad == "nan_first":
            frames[0, 1, 2] = np.nan
        elif bad == "nan_later":
            frames[2, 1, 2] = np.nan
        elif bad == "inf":
            frames[3, 0, 0] = np.inf
        elif bad == "negative":
            frames[1, 2, 4] = -0.25
        elif bad == "decreasing":
            times = np.array([0, 1000, 900, 3000], np.int64)
        if bad == "shape":
            f.process(bad_packet(frames, times))
            f.process(bad_packet(np.zeros((1, 4, 5), np.float32), np.array([5000]),
                                 Geometry(5, 3)))
        elif bad == "decreasing_across":
            f.process(bad_packet(frames, times))
            f.process(bad_packet(frames[:1], np.array([2500])))
        else:
            f.process(bad_packet(frames, times))
            f.flush()
    if bad in ("nan_later", "negative"):
        assert "pixel (x=" in str(info.value)


def test_bad_pixel_in_a_full_chunk_reported_first_in_pixel_order():
    # 8 x 40 frames: the scan's full chunks; events before the bad pixel, a later bad one too
    frames = np.full((4, 8, 40), 0.5, np.float32)
    frames[1:, 0, :10] = 2.0                       # fires before the bad pixel
    frames[2, 5, 33] = np.nan
    frames[2, 7, 1] = -1.0
    times = np.array([0, 1000, 2000, 3000], np.int64)
    f = Emulator()
    f.setup(Emulator.Params(interpolation="linear"), Context())
    with pytest.raises(DataError, match=r"frame 2 .*not finite .*pixel \(x=33, y=5\)"):
        f.process(bad_packet(frames, times))
