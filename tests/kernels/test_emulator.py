"""The emulator kernel against the slow reference (tests/naive/emulator.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evchain.core.filter import Context
from evchain.core.packets import EventPacket, FramePacket, Geometry
from evchain.filters.emulator import Emulator
from tests.naive.emulator import emulate as naive


def run_filter(frames, times, cut=None, strip=None, block=None, **params):
    n, h, w = frames.shape
    g = Geometry(w, h)
    f = Emulator()
    f.record_float_times = True
    f.strip_pixels = strip
    f.block_intervals = block
    f.setup(Emulator.Params(**params), Context(seed=3))
    cut = cut or [n]
    outs, i = [], 0
    t_end_all = int(times[-1]) + 1
    for k in cut:
        j = min(i + k, n)
        t_start = int(times[i]) if i < n else t_end_all
        t_end = int(times[j]) if j < n else t_end_all
        outs.append(f.process(FramePacket(geometry=g, t_start=t_start, t_end=t_end,
                                          frames=frames[i:j], t=times[i:j])))
        i = j
    outs.append(f.flush())
    ev = EventPacket.concat(outs).validate()
    tf = np.concatenate(f.float_times) if f.float_times else np.zeros(0)
    return ev, tf


def compare(frames, times, c=0.2, strip=None, block=None, cut=None, **params):
    cubic = params.get("interpolation", "cubic") == "cubic"
    ev, tf = run_filter(frames, times, cut=cut, strip=strip, block=block, threshold_on=c,
                        threshold_off=c, **params)
    x, y, ti, tfn, p = naive(frames, times, c, c, eps=params.get("eps", 1e-3),
                             tol=params.get("tie_tolerance", 1e-6), cubic=cubic,
                             refractory_us=params.get("refractory_us", 0.0),
                             cap=params.get("max_events_per_interval"))
    assert len(ev) == len(x)
    np.testing.assert_allclose(tf, tfn, atol=1e-6)
    np.testing.assert_array_equal(ev.x, x)
    np.testing.assert_array_equal(ev.y, y)
    np.testing.assert_array_equal(ev.p, p)
    np.testing.assert_array_equal(ev.t, ti)
    return ev


def random_stream(seed, n=12, h=5, w=7):
    rng = np.random.default_rng(seed)
    frames = np.exp(rng.normal(-1.5, 1.0, (n, h, w))).astype(np.float32)
    frames[rng.random((n, h, w)) < 0.1] = 0.0
    times = np.cumsum(rng.integers(50, 3000, n)).astype(np.int64)
    return frames, times


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
@pytest.mark.parametrize("seed", range(4))
def test_random_matches_naive(seed, interpolation):
    frames, times = random_stream(seed)
    ev = compare(frames, times, c=0.3, interpolation=interpolation)
    assert len(ev) > 50          # the comparison is not vacuous


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_refractory_and_cap_match_naive(interpolation):
    frames, times = random_stream(11, n=15)
    compare(frames, times, c=0.15, interpolation=interpolation, refractory_us=400.0)
    compare(frames, times, c=0.15, interpolation=interpolation, max_events_per_interval=2)


def test_hard_inputs_match_naive():
    # exact returns to earlier levels, zeros, large jumps, equal neighbours
    eps = 1e-3
    base = np.float32(0.25)
    lev = np.exp(np.log(np.float64(base) + eps) + 0.2 * np.array([0, 1, 2, 1, 0, -1, 0, 3, 0]))
    col = (lev - eps).astype(np.float32)
    n = len(col)
    frames = np.zeros((n, 3, 4), np.float32)
    frames[:, 0, 0] = col
    frames[:, 0, 1] = base
    frames[:, 1, 2] = np.where(np.arange(n) % 2, 1.0, 0.0)
    frames[:, 2, 3] = np.linspace(0, 2, n)
    times = np.arange(n, dtype=np.int64) * 1000
    for interp in ("linear", "cubic"):
        ev = compare(frames, times, c=0.2, interpolation=interp)
        at = (ev.x == 0) & (ev.y == 0)
        # ramp by exact thresholds: +2, -1, -1, -1, +1, +3, -3 => one event per threshold
        assert list(ev.p[at]) == [1, 1, -1, -1, -1, 1, 1, 1, 1, -1, -1, -1]
        assert not ((ev.x == 1) & (ev.y == 0)).any()


def test_packet_cuts_identical():
    frames, times = random_stream(5, n=20)
    for interp in ("linear", "cubic"):
        ref, tref = run_filter(frames, times, interpolation=interp, threshold_on=0.25,
                               threshold_off=0.25, noise_rate_hz=50.0)
        for cut in ([1] * 20, [3, 1, 7, 2, 7], [2, 0, 5, 13]):
            got, tgot = run_filter(frames, times, cut=cut, interpolation=interp,
                                   threshold_on=0.25, threshold_off=0.25, noise_rate_hz=50.0)
            for name in ("x", "y", "t", "p"):
                np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))
            np.testing.assert_array_equal(tgot, tref)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_full_chunks_and_log_cache_match_naive(interpolation):
    # 9 x 23 = 207 pixels: three full scan chunks of 64 plus a remainder; a smooth drift makes
    # many pixels fire in consecutive intervals (log cache), a few fire in isolation
    rng = np.random.default_rng(21)
    n, h, w = 10, 9, 23
    base = np.exp(rng.normal(-1.0, 0.7, (h, w)))
    drift = rng.normal(0.0, 0.25, (h, w))
    k = np.arange(n)[:, None, None]
    frames = (base * np.exp(drift * k + 0.05 * np.sin(1.3 * k))).astype(np.float32)
    frames[:, 4, 5:9] = 0.0                                  # zeros inside a chunk
    frames[6, 8, 20] *= 4.0                                  # an isolated jump, last chunk
    times = np.cumsum(rng.integers(200, 2000, n)).astype(np.int64)
    ev = compare(frames, times, c=0.2, interpolation=interpolation)
    assert len(ev) > 300
    for cut in ([1] * n, [4, 3, 3]):          # the cache across packet boundaries
        got, _ = run_filter(frames, times, cut=cut, interpolation=interpolation,
                            threshold_on=0.2, threshold_off=0.2)
        np.testing.assert_array_equal(got.t, ev.t)
        np.testing.assert_array_equal(got.x, ev.x)


def _pieces(rng, n):
    """Monotone cubic pieces (Fritsch-Carlson limited slopes) and levels inside them, with
    hard cases: zero end slopes (extrema), slopes at the 3x limit, levels at the ends, tiny and
    huge steps."""
    from tests.naive.emulator import _slope3

    scale = rng.choice([1e-9, 1e-3, 0.3, 5.0], n)
    nodes = np.cumsum(rng.normal(0, 1, (n, 4)), axis=1) * scale[:, None]
    la, lb = nodes[:, 1], nodes[:, 2]
    m0 = np.array([_slope3(q[1] - q[0], q[2] - q[1], 1.0, 1.0) for q in nodes])
    m1 = np.array([_slope3(q[2] - q[1], q[3] - q[2], 1.0, 1.0) for q in nodes])
    kind = rng.integers(0, 5, n)
    m0[kind == 1] = 0.0
    m1[kind == 2] = 0.0
    lim = 3.0 * (lb - la)
    m0[kind == 3] = lim[kind == 3]
    m1[kind == 3] = lim[kind == 3]
    m0[kind == 4] = m1[kind == 4] = 0.0
    frac = rng.random(n)
    frac[rng.random(n) < 0.05] = 0.0
    frac[rng.random(n) < 0.05] = 1.0
    frac[rng.random(n) < 0.05] = 1e-12
    frac[rng.random(n) < 0.05] = 1.0 - 1e-12
    return la + frac * (lb - la), la, lb, m0, m1


def test_solve_crossing_matches_bisection():
    # the cubic crossing solve (Newton with an error-bound stop) against plain bisection
    from evchain.kernels.emulator_crossings import solve_crossing
    from tests.naive.emulator import _hermite, _solve

    rng = np.random.default_rng(4)
    lev, la, lb, m0, m1 = _pieces(rng, 4000)
    worst = 0.0
    for q in range(len(lev)):
        s = solve_crossing(lev[q], la[q], lb[q], m0[q], m1[q], True)
        ref = _solve(lev[q], la[q], lb[q], m0[q], m1[q], True)
        assert np.isfinite(s) and 0.0 <= s <= 1.0
        # the piece at s is at the level to float precision of the values involved
        span = abs(la[q]) + abs(lb[q]) + abs(m0[q]) + abs(m1[q])
        assert abs(_hermite(s, la[q], lb[q], m0[q], m1[q]) - lev[q]) <= 1e-9 * span + 1e-300
        # where the root is well conditioned (the piece not flat there), s itself is exact
        slope = (_hermite(ref + 1e-7, la[q], lb[q], m0[q], m1[q])
                 - _hermite(ref - 1e-7, la[q], lb[q], m0[q], m1[q])) / 2e-7
        if abs(slope) > 1e-3 * abs(lb[q] - la[q]):
            worst = max(worst, abs(s - ref))
    assert worst < 1e-9
    # equal end values and levels outside the piece
    assert solve_crossing(1.0, 2.0, 2.0, 0.0, 0.0, True) == 0.0
    assert solve_crossing(3.0, 2.0, 2.5, 0.1, 0.1, True) == 1.0
    assert solve_crossing(1.0, 2.0, 2.5, 0.1, 0.1, True) == 0.0


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_many_crossings_in_one_interval_match_naive(interpolation):
    # ~34 crossings per pixel in one interval, ~4 900 in all: more than the first event
    # buffer (4 096), so the kernel stops, grows and resumes mid-interval; with an empty
    # interval (equal frames) in between and the refractory period and the cap
    h, w = 12, 12
    rng = np.random.default_rng(8)
    lo_ = rng.uniform(0.0, 0.002, (h, w))
    frames = np.stack([lo_, lo_, 1.0 + 0 * lo_, 1.0 + 0 * lo_, lo_]).astype(np.float32)
    times = np.array([0, 1000, 1500, 2700, 3100], np.int64)
    ev = compare(frames, times, c=0.2, interpolation=interpolation)
    assert len(ev) > 4096
    compare(frames, times, c=0.2, interpolation=interpolation, refractory_us=30.0)
    compare(frames, times, c=0.2, interpolation=interpolation, max_events_per_interval=5)
    # one frame per packet: the work arrays grown in one call are reused by the next ones,
    # and the events held at a slice end are written first by the next call
    cut, tf_cut = run_filter(frames, times, cut=[1] * 5, threshold_on=0.2, threshold_off=0.2,
                             interpolation=interpolation)
    whole, tf_whole = run_filter(frames, times, threshold_on=0.2, threshold_off=0.2,
                                 interpolation=interpolation)
    for k in "xytp":
        np.testing.assert_array_equal(getattr(cut, k), getattr(whole, k))
    np.testing.assert_array_equal(tf_cut, tf_whole)


def test_batched_times_match_bisection():
    # _times (lockstep Newton over all crossings, checked step, fallback) against bisection
    from evchain.kernels.emulator_crossings import _times
    from evchain.kernels.emulator_state import ROW, S_LAST
    from tests.naive.emulator import _hermite, _solve

    rng = np.random.default_rng(5)
    lev, la, lb, m0, m1 = _pieces(rng, 4000)
    n = len(lev)
    piece = np.empty((7, n))
    piece[:5] = lev, la, lb, m0, m1
    piece[6] = -1e300                     # the pixels' last_t, as the rule lists it
    for cubic in (True, False):
        ui = np.arange(n, dtype=np.int64)
        utf = np.empty(n)
        up_ = np.ones(n, np.int8)
        rows = np.zeros((n, ROW))             # the pixels' state rows (only last_t used)
        rows[:, S_LAST] = -1e300
        assert _times(0, n, cubic, 0.0, 1.0, 0.0, ui, utf, up_, piece.copy(), rows) == n
        assert np.array_equal(rows[:, S_LAST], utf)
        worst = 0.0
        for q in range(n):
            ref = _solve(lev[q], la[q], lb[q], m0[q], m1[q], cubic)
            assert np.isfinite(utf[q]) and 0.0 <= utf[q] <= 1.0
            slope = (_hermite(ref + 1e-7, la[q], lb[q], m0[q], m1[q])
                     - _hermite(ref - 1e-7, la[q], lb[q], m0[q], m1[q])) / 2e-7
            if not cubic or abs(slope) > 1e-3 * abs(lb[q] - la[q]):
                worst = max(worst, abs(utf[q] - ref))
        assert worst < 1e-9


def test_chunk_mask_and_bits_match_scalar_test():
    # the scan's candidate mask (vectorised compares) and its set bits read off by cttz
    # against the scalar gate test: random values, values equal to the gates, NaN, inf,
    # negative values, LO_NONE gates, all-clear and all-set chunks
    from numba import njit

    from evchain.kernels.emulator import CHUNK, _chunk_mask
    from evchain.kernels.emulator_state import LO_NONE
    from evchain.kernels.intrinsics import cttz

    @njit
    def bits(m):
        out = []
        while m != 0:
            out.append(np.int64(cttz(m)))
            m &= m - np.uint64(1)
        return out

    rng = np.random.default_rng(4)
    for trial in range(300):
        hi = rng.uniform(0.5, 1.0, CHUNK).astype(np.float32)
        lo = rng.uniform(0.0, 0.5, CHUNK).astype(np.float32)
        lo[rng.random(CHUNK) < 0.1] = np.float32(LO_NONE)
        f = rng.uniform(-0.1, 1.1, CHUNK).astype(np.float32)
        if trial % 3 == 0:
            f = 0.5 * (hi + lo)                                  # all clear
        if trial % 7 == 0:
            f = hi + 1                                           # all set
        k = rng.integers(0, CHUNK, 6)
        f[k[0]] = hi[k[0]]
        f[k[1]] = lo[k[1]]
        if trial % 2:
            f[k[2]] = np.nan
            f[k[3]] = np.inf
            f[k[4]] = -np.inf
            f[k[5]] = 0.0
        ref = [q for q in range(CHUNK) if not (f[q] < hi[q] and f[q] > lo[q])]
        m = _chunk_mask(f, hi, lo)
        assert (m == 0) == (not ref)
        assert list(bits(np.uint64(m))) == ref


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_exact_return_to_first_level_with_zero_tolerance(interpolation):
    # l0 and the rule's logs come from one function (veclog): a pixel back at exactly its first
    # intensity is exactly at its first level, so with tol = 0 its last OFF event fires
    rng = np.random.default_rng(5)
    first = rng.uniform(0.05, 1.0, (40, 50)).astype(np.float32)
    frames = np.stack([first, first * np.float32(1.6), first])
    times = np.array([0, 1000, 2000], np.int64)
    ev, _ = run_filter(frames, times, threshold_on=0.2, threshold_off=0.2, tie_tolerance=0.0,
                       interpolation=interpolation)
    on = np.zeros(first.shape, np.int64)
    off = np.zeros(first.shape, np.int64)
    np.add.at(on, (ev.y[ev.p > 0], ev.x[ev.p > 0]), 1)
    np.add.at(off, (ev.y[ev.p < 0], ev.x[ev.p < 0]), 1)
    assert on.min() == 2
    np.testing.assert_array_equal(off, on)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_strips_match_naive(interpolation):
    # 17 x 30 = 510 pixels in strips of 64 or 192 (the last one partial), blocks of 1, 3 or 8
    # intervals on one strip before the next: the same events as the reference, in its order
    rng = np.random.default_rng(8)
    n, h, w = 14, 17, 30
    base = np.exp(rng.normal(-1.0, 0.7, (h, w)))
    drift = rng.normal(0.0, 0.25, (h, w))
    k = np.arange(n)[:, None, None]
    frames = (base * np.exp(drift * k + 0.05 * np.sin(1.3 * k))).astype(np.float32)
    frames[rng.random((n, h, w)) < 0.03] = 0.0
    times = np.cumsum(rng.integers(200, 2000, n)).astype(np.int64)
    for strip, block, cut in ((64, 8, None), (192, 3, [5, 1, 8]), (64, 1, [1] * n),
                              (64, 3, [9, 5])):
        ev = compare(frames, times, c=0.2, strip=strip, block=block, cut=cut,
                     interpolation=interpolation, noise_rate_hz=0.0, refractory_us=300.0)
        assert len(ev) > 800
    ref, _ = run_filter(frames, times, threshold_on=0.2, threshold_off=0.2, noise_rate_hz=80.0,
                        interpolation=interpolation)
    got, _ = run_filter(frames, times, strip=64, block=3, cut=[4, 10], threshold_on=0.2,
                        threshold_off=0.2, noise_rate_hz=80.0, interpolation=interpolation)
    for name in ("x", "y", "t", "p"):        # noise last in each interval, as in one strip
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))


@given(st.integers(1, 4_000_000), st.integers(1, 2000).map(lambda c: 64 * c))
def test_strip_length_cuts_into_fewest_equal_strips(npix, most):
    from evchain.kernels.emulator_state import CHUNK, strip_length
    strip = strip_length(npix, most)
    count = -(-npix // strip)
    assert strip % CHUNK == 0 and strip <= max(most, CHUNK)
    assert count == -(-npix // most)                   # no more strips than needed
    assert npix - (count - 1) * strip > strip - CHUNK * count   # the last one nearly as long


def test_strip_length_examples():
    from evchain.kernels.emulator_state import strip_length
    assert strip_length(320 * 240, 32768) == 25600     # three strips
    assert strip_length(1280 * 720, 32768) == 31808    # 29 strips, the last 30 976 pixels
    assert strip_length(510, 192) == 192


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_rows_filled_on_first_use_match_naive(interpolation):
    # set-up writes only the gates; a chunk's state rows are filled when the scan first finds
    # a candidate in it. Pixels whose change starts at different frames (some never), per-pixel
    # thresholds (mismatch), packet cuts and strips: the same events as the reference with
    # those thresholds; chunks (here image rows of 64 pixels) that never change stay unfilled
    from evchain.kernels.emulator_state import CHUNK

    rng = np.random.default_rng(21)
    n, h, w = 16, 9, CHUNK
    base = np.exp(rng.normal(-1.0, 0.6, (h, w)))
    start = rng.integers(1, n + 4, (h, w))                 # first changing frame (>= n: never)
    start[[2, 6]] = n                                      # two rows never change
    k = np.arange(n)[:, None, None]
    ramp = np.maximum(k - start[None], 0) * rng.normal(0.0, 0.3, (h, w))
    frames = (base * np.exp(ramp)).astype(np.float32)
    times = np.cumsum(rng.integers(200, 2000, n)).astype(np.int64)
    cubic = interpolation == "cubic"
    for strip, block, cut in ((None, None, None), (64, 3, [3, 1, 7, 5])):
        f = Emulator()
        f.record_float_times = True
        f.strip_pixels = strip
        f.block_intervals = block
        f.setup(Emulator.Params(threshold_on=0.25, threshold_off=0.2, mismatch_sigma=0.1,
                                interpolation=interpolation), Context(seed=3))
        outs, i = [], 0
        for m in cut or [n]:
            j = min(i + m, n)
            t_end = int(times[j]) if j < n else int(times[-1]) + 1
            outs.append(f.process(FramePacket(geometry=Geometry(w, h), t_start=int(times[i]),
                                              t_end=t_end, frames=frames[i:j], t=times[i:j])))
            i = j
        outs.append(f.flush())
        ev = EventPacket.concat(outs).validate()
        con, coff = f.thresholds
        assert np.ptp(con) > 0.01                      # per-pixel thresholds
        x, y, ti, tfn, p = naive(frames, times, con, coff, cubic=cubic)
        assert len(ev) == len(x) > 300
        np.testing.assert_allclose(np.concatenate(f.float_times), tfn, atol=1e-6)
        for name, want in (("x", x), ("y", y), ("p", p), ("t", ti)):
            np.testing.assert_array_equal(getattr(ev, name), want)
        filled = f._state["ready"][:-1] == 1               # per image row here
        assert filled[ev.y].all()                      # a row with events had candidates
        assert not filled[[2, 6]].any()                # never changed: never a candidate


@pytest.mark.parametrize("strip, block", [(64, 8), (128, 2), (None, None)])
def test_first_bad_pixel_across_strips(strip, block):
    # a bad value in a later strip at an earlier frame comes first; in the same frame, the
    # lower pixel
    from evchain.errors import DataError

    frames = np.full((6, 10, 40), 0.5, np.float32)
    frames[1:, :, ::3] = 2.0                       # events everywhere before the bad values
    frames[4, 0, 5] = -1.0                         # strip 0, frame 4
    frames[3, 9, 30] = np.nan                      # last strip, frame 3: first
    frames[3, 6, 2] = -2.0                         # frame 3, a lower pixel in an earlier strip
    times = np.arange(6, dtype=np.int64) * 1000
    with pytest.raises(DataError, match=r"frame 3 .*negative at pixel \(x=2, y=6\)"):
        run_filter(frames, times, strip=strip, block=block, threshold_on=0.2,
                   threshold_off=0.2)
    frames[3, 6, 2] = 0.5
    with pytest.raises(DataError, match=r"frame 3 .*not finite .*pixel \(x=30, y=9\)"):
        run_filter(frames, times, strip=strip, block=block, threshold_on=0.2,
                   threshold_off=0.2)


def test_count_overflow_is_an_error():
    # a pixel's counts are int32: a move past MAX_COUNT is refused, not wrapped. The counts
    # are set to the limit after a first packet (n_on = n_off: the reference level stays at
    # l0 when c_on = c_off), then the next crossing passes it
    from evchain.errors import DataError
    from evchain.kernels.emulator_state import C_NOFF, C_NON, MAX_COUNT

    frames = np.full((6, 2, 64), 0.5, np.float32)
    frames[1:3, 0, 3] = 0.3                        # a candidate: its row is filled
    frames[3:, 0, 3] = 0.9                         # beyond its gates again: a crossing
    times = np.arange(6, dtype=np.int64) * 1000
    g = Geometry(64, 2)
    f = Emulator()
    f.setup(Emulator.Params(threshold_on=0.2, threshold_off=0.2), Context(seed=0))
    f.process(FramePacket(geometry=g, t_start=0, t_end=3000, frames=frames[:3], t=times[:3]))
    assert f._state["ready"][0] == 1
    f._counts[3, C_NON] = MAX_COUNT
    f._counts[3, C_NOFF] = MAX_COUNT
    with pytest.raises(DataError, match=r"\[3000, 6001\) us, .*2\^31 - 1 reference moves"):
        f.process(FramePacket(geometry=g, t_start=3000, t_end=6001, frames=frames[3:],
                              t=times[3:]))


@st.composite
def level_streams(draw):
    """Frames on and between a pixel's exact levels (ties), zeros, jumps of several levels
    and quiet pixels, at uneven frame times: every kind of the rule's first pass (no
    crossing, one ON or OFF event, several) and its log cache's hits and misses."""
    n = draw(st.integers(3, 9))
    h = draw(st.integers(1, 3))
    w = draw(st.integers(1, 5))
    eps = 1e-3
    start = draw(st.floats(0.01, 1.0))
    steps = draw(st.lists(st.sampled_from([-3, -1, -1, 0, 0, 0, 0.5, 1, 1, 2]), min_size=n * h * w,
                          max_size=n * h * w))
    k = np.cumsum(np.array(steps, np.float64).reshape(n, h, w), axis=0)
    frames = (np.exp(np.log(start + eps) + 0.2 * k) - eps).astype(np.float32)
    frames = np.maximum(frames, 0)
    zero = draw(st.lists(st.booleans(), min_size=n * h * w, max_size=n * h * w))
    frames[np.array(zero).reshape(n, h, w) & (np.arange(n * h * w).reshape(n, h, w) % 7 == 0)] = 0
    dts = draw(st.lists(st.integers(20, 3000), min_size=n, max_size=n))
    return frames, np.cumsum(np.array(dts, np.int64))


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
@settings(max_examples=40, deadline=None)
@given(stream=level_streams(), cap=st.sampled_from([None, 1, 2]),
       tol=st.sampled_from([0.0, 1e-6]), refractory=st.sampled_from([0.0, 150.0]))
def test_first_pass_kinds_match_naive(interpolation, stream, cap, tol, refractory):
    frames, times = stream
    compare(frames, times, c=0.2, interpolation=interpolation, max_events_per_interval=cap,
            tie_tolerance=tol, refractory_us=refractory)


def test_slope3_matches_naive():
    # the kernel's select form against the reference's branches: random secants, zeros,
    # opposite signs, ties at the clip and infinities (bit for bit)
    from evchain.kernels.emulator_crossings import slope3
    from tests.naive.emulator import _slope3

    rng = np.random.default_rng(4)
    d = np.concatenate([rng.normal(0, 1, 400), [0.0, -0.0, 1.0, -1.0, 3.0, np.inf, -np.inf]])
    h = rng.uniform(0.01, 5, 40)
    hard = [(1.0, 1.0, 1.0, 1.0), (1.0, 3.0, 1.0, 1.0), (1.0, 0.0, 2.0, 1.0),
            (np.inf, 1.0, 1.0, 1.0), (-2.0, -1e-300, 1.0, 3.0)]
    cases = hard + [(d[i], d[j], h[i % 40], h[j % 40])
                    for i, j in rng.integers(0, len(d), (3000, 2))]
    for d1, d2, h1, h2 in cases:
        assert slope3(d1, d2, h1, h2) == _slope3(d1, d2, h1, h2), (d1, d2, h1, h2)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_more_candidates_than_first_room_match_naive(interpolation):
    # 5 120 pixels firing in one strip and interval: more than the first pass's first room
    # (CV_START = 4 096), so its arrays grow mid-call
    from evchain.kernels.emulator_state import CV_START

    h, w = 64, 80
    assert h * w > CV_START
    rng = np.random.default_rng(12)
    base = rng.uniform(0.05, 1.0, (h, w))
    frames = np.stack([base, base * 1.6, base * 0.5, base * 2.5, base]).astype(np.float32)
    times = np.array([0, 1000, 1800, 3100, 4000], np.int64)
    ev = compare(frames, times, c=0.2, interpolation=interpolation)
    assert len(ev) > 4 * h * w
