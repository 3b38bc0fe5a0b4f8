"""aps: exposure integration (motion blur), noise statistics, rolling shutter, ADC, contract."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.packets import ApsFramePacket, FramePacket, Geometry
from evchain.filters.aps import Aps, interval_weights
from evchain.testing.contract import check_filter, make_context, recut, run_filter

G = Geometry(64, 48)
IDEAL = {"shot_noise": False, "read_noise_e": 0.0, "adc_bits": 16}


def frames_of(fn, times_us, geometry: Geometry = G) -> FramePacket:
    """One packet of frames ``fn(x, y, t_us)`` at ``times_us``."""
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width].astype(np.float64)
    t = np.asarray(times_us, np.int64)
    frames = np.stack([fn(xs, ys, float(ti)) for ti in t]).astype(np.float32)
    return FramePacket(geometry=geometry, t_start=int(t[0]), t_end=int(t[-1]) + 1,
                       frames=frames, t=t)


def run_aps(params: dict, packets: list[FramePacket], seed: int = 0) -> dict:
    f = Aps()
    f.id = "aps"
    f.setup(Aps.Params(**params), make_context(packets[0].geometry, seed=seed))
    outs = run_filter(f, packets)
    whole = ApsFramePacket.concat(outs)
    return {"frames": whole.frames, "t": whole.t, "start": whole.t_exposure_start}


def ramp(x0: float, w: float, v_px_per_us: float):
    """A vertical edge from 0 (left) to 1 (right) over w px, moving right."""
    return lambda xs, ys, t: np.clip((xs - x0 - v_px_per_us * t) / w, 0.0, 1.0)


def ramp_time_average(x, x0, w, v, t1, t2):
    """Exact time average over [t1, t2] of clip((x - x0 - v t) / w, 0, 1)."""
    def g(u):  # antiderivative of clip(u / w, 0, 1)
        return np.where(u < 0, 0.0, np.where(u <= w, u * u / (2 * w), w / 2 + u - w))
    return (g(x - x0 - v * t1) - g(x - x0 - v * t2)) / (v * (t2 - t1))


def test_static_scene_gives_the_same_frame_every_time():
    img = lambda xs, ys, t: 0.2 + 0.6 * (np.sin(0.3 * xs) * np.cos(0.2 * ys)) ** 2  # noqa: E731
    pk = frames_of(img, np.arange(0, 100_000, 700))
    out = run_aps({**IDEAL, "adc_bits": 10, "rate_hz": 100, "exposure_us": 3000}, [pk])
    assert len(out["frames"]) == 10         # exposures start at 0, 10, ..., 90 ms
    want = np.floor(img(*np.mgrid[0:48, 0:64][::-1].astype(float), 0.0) * 1023 + 0.5) / 1023
    for fr in out["frames"]:
        np.testing.assert_array_equal(fr, want.astype(np.float32))
    np.testing.assert_array_equal(out["start"], np.arange(0, 100_000, 10_000))
    np.testing.assert_array_equal(out["t"], out["start"] + 3000)


def test_moving_edge_is_blurred_by_the_exact_ramp():
    # the edge moves 1 px per 100 us input frame, so the pixels' intensities are linear in
    # time between the input frames and the integral is exact
    v, x0, w = 0.01, 5.0, 3.0
    pk = frames_of(ramp(x0, w, v), np.arange(0, 4001, 100))
    out = run_aps({**IDEAL, "rate_hz": 1000, "exposure_us": 1000}, [pk])
    assert len(out["frames"]) == 4
    xs = np.arange(64, dtype=np.float64)
    for fr, s in zip(out["frames"], out["start"], strict=True):
        want = ramp_time_average(xs, x0, w, v, s, s + 1000.0)
        np.testing.assert_allclose(fr[10], want, atol=1.0 / 65535)
        np.testing.assert_array_equal(fr, np.broadcast_to(fr[10], fr.shape))
        # the blur: from fully dark to fully bright over w + v * exposure = 13 px
        lit = np.flatnonzero((fr[0] > 0) & (fr[0] < 1))
        assert lit[-1] - lit[0] + 2 == pytest.approx(w + v * 1000.0)


def test_interval_weights_integrate_linear_functions_exactly():
    rng = np.random.default_rng(1)
    for _ in range(200):
        ta, tb = sorted(rng.uniform(0, 100, 2))
        lo, hi = sorted(rng.uniform(-20, 120, 2))
        a, b = rng.uniform(-1, 2, 2)
        wa, wb = interval_weights(ta, tb, lo, hi)
        u, v = max(ta, lo), min(tb, hi)
        line = lambda t: a + (b - a) * (t - ta) / (tb - ta)  # noqa: E731,B023
        want = 0.0 if v <= u else (v - u) * (line(u) + line(v)) / 2
        assert wa * a + wb * b == pytest.approx(want, abs=1e-9)


def test_noise_statistics_are_poisson_plus_gaussian():
    mean_e, read_e, fw = 300.0, 5.0, 100_000.0
    pk = frames_of(lambda xs, ys, t: np.full_like(xs, 0.3), np.arange(0, 200_001, 2000))
    params = {"rate_hz": 50, "exposure_us": 4000, "gain_e_per_unit": 1000.0,
              "full_well_e": fw, "read_noise_e": read_e, "adc_bits": 16}
    out = run_aps(params, [pk])
    e = out["frames"].astype(np.float64) * fw       # back to electrons
    assert len(out["frames"]) == 10
    step = fw / 65535
    n = e.size
    assert abs(e.mean() - mean_e) < 4 * np.sqrt((mean_e + read_e ** 2) / n) + step / 2
    want_var = mean_e + read_e ** 2 + step ** 2 / 12
    assert e.var() == pytest.approx(want_var, rel=4 * np.sqrt(2 / n))
    # seeded: the same seed gives the same frames, another seed others
    np.testing.assert_array_equal(run_aps(params, [pk])["frames"], out["frames"])
    assert not np.array_equal(run_aps(params, [pk], seed=1)["frames"], out["frames"])
    # shot noise alone: variance = mean
    shot = run_aps({**params, "read_noise_e": 0.0}, [pk])["frames"].astype(np.float64) * fw
    assert shot.var() == pytest.approx(mean_e + step ** 2 / 12, rel=4 * np.sqrt(2 / n))


def test_rolling_shutter_skews_a_moving_vertical_edge():
    v, row_us = 0.01, 20.0   # 10 000 px/s, 20 us per row: 0.2 px per row
    pk = frames_of(ramp(5.0, 3.0, v), np.arange(0, 6001, 100))
    out = run_aps({**IDEAL, "rate_hz": 500, "exposure_us": 1000, "shutter": "rolling",
                   "row_time_us": row_us}, [pk])
    fr = out["frames"][0]
    assert out["t"][0] == out["start"][0] + 47 * 20 + 1000
    xs = np.arange(64, dtype=np.float64)
    half = [np.interp(0.5, row, xs) for row in fr.astype(np.float64)]
    slope = np.polyfit(np.arange(48), half, 1)[0]
    assert slope == pytest.approx(v * row_us, rel=1e-4)
    # each row is the global-shutter blur of its own window
    for r in (0, 17, 47):
        want = ramp_time_average(xs, 5.0, 3.0, v, r * row_us, r * row_us + 1000.0)
        np.testing.assert_allclose(fr[r], want, atol=1.0 / 65535)


@pytest.mark.parametrize("bits", [8, 10])
def test_quantisation_and_clipping(bits):
    levels = (1 << bits) - 1
    vals = np.linspace(0, 1.3, 64)
    pk = frames_of(lambda xs, ys, t: vals[xs.astype(int)], np.arange(0, 20_001, 1000))
    out = run_aps({**IDEAL, "adc_bits": bits, "rate_hz": 100, "exposure_us": 2000}, [pk])
    want = np.floor(np.minimum(vals, 1.0) * levels + 0.5) / levels
    np.testing.assert_allclose(out["frames"][0][0], want, atol=1e-7)
    assert len(np.unique(out["frames"])) <= levels + 1


def test_contract_and_cuts():
    pk = frames_of(ramp(5.0, 3.0, 0.002), np.arange(0, 30_000, 250))
    packets = recut([pk], [7_000, 7_001, 15_500])
    params = {"rate_hz": 400, "exposure_us": 1500, "read_noise_e": 10.0}
    check_filter(Aps, params, packets)
    check_filter(Aps, {**params, "shutter": "rolling", "row_time_us": 3.0}, packets)


def test_bad_parameters_are_rejected():
    with pytest.raises(ValueError, match="frame interval"):
        Aps.Params(rate_hz=100, exposure_us=20_000)
    with pytest.raises(ValueError, match="row_time_us"):
        Aps.Params(shutter="rolling")
