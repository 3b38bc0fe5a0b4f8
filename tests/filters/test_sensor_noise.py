"""sensor_noise: measured rates against the parameters, hot pixels, seeds, cuts, empty input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.filters.sensor_noise import BLOCK_US, SensorNoise
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import moving_edge_events, random_events

G = Geometry(64, 48)
NPIX = G.width * G.height
#: a p-value below this fails a statistical test (each test here draws fixed seeds, so a
#: pass or fail is reproducible; the threshold only says how unlikely a pass by luck is)
ALPHA = 1e-4


def run(params: dict, packets: list[EventPacket], seed: int = 0,
        filter_id: str = "sensor_noise") -> tuple[EventPacket, SensorNoise]:
    f = SensorNoise()
    f.id = filter_id
    f.setup(SensorNoise.Params(**params), Context(seed=seed))
    outs = [f.process(p) for p in packets]
    last = f.flush()
    if last is not None:
        outs.append(last)
    out = EventPacket.concat(outs)
    out.validate("sensor_noise output")
    return out, f


def silence(t0: int, t1: int, n: int = 7) -> list[EventPacket]:
    """An empty input stream over [t0, t1) in ``n`` packets."""
    edges = np.linspace(t0, t1, n + 1).astype(np.int64)
    return [EventPacket.empty(G, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:],
                                                                  strict=True)]


def as_tuples(ev: EventPacket) -> list[tuple]:
    return list(zip(ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), ev.p.tolist(), strict=True))


def test_off_by_default_passes_the_packet_unchanged():
    ev = random_events(500, G, 0, 50_000, seed=1)
    f = SensorNoise()
    f.id = "sensor_noise"
    f.setup(SensorNoise.Params(), Context())
    assert f.process(ev) is ev


def test_shot_noise_rate_is_poisson_with_the_given_rate():
    rate, span_s = 2.0, 10.0
    out, _ = run({"shot_rate_hz": rate}, silence(0, int(span_s * 1e6)))
    mean = rate * NPIX * span_s                                # 61 440 expected
    # the total count is Poisson: within 4 standard deviations
    assert abs(len(out) - mean) < 4 * math.sqrt(mean)
    # per pixel: Poisson counts of equal mean (dispersion test, chi-square with NPIX-1 dof)
    counts = np.bincount(out.y.astype(np.int64) * G.width + out.x, minlength=NPIX)
    chi2 = ((counts - counts.mean()) ** 2).sum() / counts.mean()
    assert stats.chi2.sf(chi2, NPIX - 1) > ALPHA and stats.chi2.cdf(chi2, NPIX - 1) > ALPHA
    # uniform in time: counts per 100 ms against a flat expectation
    per_bin = np.bincount(out.t // 100_000, minlength=int(span_s * 10))
    assert stats.chisquare(per_bin).pvalue > ALPHA
    # ON and OFF equally likely
    assert stats.binomtest(int((out.p > 0).sum()), len(out), 0.5).pvalue > ALPHA


def test_leak_rates_spread_log_normally_around_the_mean():
    out, f = run({"leak_rate_hz": 0.5, "leak_spread_decades": 0.2}, silence(0, 1000))
    r = f.leak_rates_hz
    assert r.shape == (NPIX,) and np.all(r > 0)
    # array mean = the parameter (the factor's mean is 1): within 4 standard errors
    assert abs(r.mean() - 0.5) < 4 * r.std() / math.sqrt(NPIX)
    # the spread of log10 is the parameter; its estimate has standard error sigma/sqrt(2n)
    assert abs(np.log10(r).std() - 0.2) < 4 * 0.2 / math.sqrt(2 * NPIX)
    # spread 0: every pixel at the mean rate
    _, f0 = run({"leak_rate_hz": 0.5, "leak_spread_decades": 0.0}, silence(0, 1000))
    assert np.allclose(f0.leak_rates_hz, 0.5)


def test_leak_events_are_on_and_regular_at_each_pixels_rate():
    span_s, jitter = 20.0, 0.1
    out, f = run({"leak_rate_hz": 1.0, "leak_jitter": jitter}, silence(0, int(span_s * 1e6)))
    assert np.all(out.p == 1)                                  # leak events are ON
    pix = out.y.astype(np.int64) * G.width + out.x
    counts = np.bincount(pix, minlength=NPIX)
    expected = f.leak_rates_hz * span_s                        # ~20 per pixel
    # a renewal process with a random start: per pixel the count is the expected one within
    # one event plus the jitter accumulated over the intervals (4 standard deviations)
    assert np.all(np.abs(counts - expected) <= 1 + 4 * jitter * np.sqrt(expected))
    assert abs(counts.sum() - expected.sum()) < 4 * math.sqrt(NPIX) * (0.5 + jitter * 5)
    # intervals at one pixel: mean 1/rate, relative spread = the jitter
    order = np.lexsort((out.t, pix))
    t, p = out.t[order], pix[order]
    same = p[1:] == p[:-1]
    rel = np.diff(t)[same] / (1e6 / f.leak_rates_hz[p[1:][same]])
    assert abs(rel.mean() - 1) < 4 * jitter / math.sqrt(len(rel)) + 1e-5
    assert abs(rel.std() - jitter) < 0.1 * jitter


def test_hot_pixels_fire_only_where_chosen_at_the_given_rate():
    rate, span_s = 400.0, 5.0
    out, f = run({"hot_pixel_fraction": 0.005, "hot_pixel_rate_hz": rate},
                 silence(0, int(span_s * 1e6)))
    hot = f.hot_pixels
    assert len(hot) == round(0.005 * NPIX) == 15 and len(set(hot.tolist())) == 15
    pix = out.y.astype(np.int64) * G.width + out.x
    assert set(pix.tolist()) == set(hot.tolist())              # every hot pixel, nothing else
    counts = np.bincount(pix, minlength=NPIX)[hot]
    assert stats.chisquare(counts).pvalue > ALPHA              # the same rate at each
    mean = rate * span_s * len(hot)
    assert abs(len(out) - mean) < 4 * math.sqrt(mean)
    assert stats.binomtest(int((out.p > 0).sum()), len(out), 0.5).pvalue > ALPHA


def test_same_seed_same_events_and_processes_independent():
    params = {"leak_rate_hz": 5.0, "shot_rate_hz": 3.0, "hot_pixel_fraction": 0.002,
              "hot_pixel_rate_hz": 300.0}
    stream = silence(0, 700_000)
    a, fa = run(params, stream, seed=4)
    b, _ = run(params, stream, seed=4)
    c, fc = run(params, stream, seed=5)
    assert as_tuples(a) == as_tuples(b)
    assert as_tuples(a) != as_tuples(c)
    assert not np.array_equal(fa.hot_pixels, fc.hot_pixels)
    # a stage with another id draws other noise
    d, _ = run(params, stream, seed=4, filter_id="noise2")
    assert as_tuples(a) != as_tuples(d)
    # turning shot noise off leaves the leak's and the hot pixels' events as they were
    e, _ = run({**params, "shot_rate_hz": 0.0}, stream, seed=4)
    assert set(as_tuples(e)) <= set(as_tuples(a))
    assert len(a) - len(e) > 0.5 * 3.0 * NPIX * 0.7


def test_cuts_do_not_change_the_output_and_input_comes_first_at_equal_times():
    params = {"leak_rate_hz": 20.0, "shot_rate_hz": 20.0, "hot_pixel_fraction": 0.01,
              "hot_pixel_rate_hz": 2000.0}
    # input events at every µs of a short stretch, so that noise falls on the same times
    edge = moving_edge_events(300.0, 0.0, G, duration_us=3 * BLOCK_US)
    dense = random_events(20_000, G, 95_000, 105_000, seed=2)
    merged = EventPacket(geometry=G, t_start=0, t_end=3 * BLOCK_US,
                         **{c: np.concatenate([getattr(edge, c), getattr(dense, c)])
                            for c in EventPacket.columns})
    merged = merged.select(np.argsort(merged.t, kind="stable"))
    ref, _ = run(params, [merged])
    for cuts in ([50_000, 100_000, 100_001, 250_000], list(range(7, 300_000, 9_973)),
                 [99_999, 100_000, 200_000, 200_001]):
        got, _ = run(params, recut([merged], cuts))
        assert as_tuples(got) == as_tuples(ref)
    # every input event is there, in its order, before any noise event of the same time
    n_in = len(merged)
    assert len(ref) > n_in
    from_input = np.zeros(len(ref), bool)
    # the input's events are a subsequence of the output in the same order
    k = 0
    rows = as_tuples(ref)
    want = as_tuples(merged)
    for i, row in enumerate(rows):
        if k < n_in and row == want[k]:
            from_input[i] = True
            k += 1
    assert k == n_in
    t = ref.t
    tie = t[1:] == t[:-1]
    mixed = tie & (from_input[1:] != from_input[:-1])
    assert mixed.sum() > 100                                   # the test has ties to break
    assert not np.any(tie & ~from_input[:-1] & from_input[1:])  # no input event after noise


def test_contract_with_every_process_on():
    stream = recut([random_events(2000, G, 0, 250_000, seed=7)], [80_000, 160_000])
    check_filter(SensorNoise, {"leak_rate_hz": 30.0, "shot_rate_hz": 10.0,
                               "hot_pixel_fraction": 0.01, "hot_pixel_rate_hz": 800.0}, stream)


def test_empty_and_zero_length_packets():
    params = {"shot_rate_hz": 50.0}
    out, _ = run(params, [EventPacket.empty(G, 1000, 1000)])
    assert len(out) == 0
    out, _ = run(params, [EventPacket.empty(G, 1000, 1000), EventPacket.empty(G, 1000, 61_000),
                          EventPacket.empty(G, 61_000, 61_000)])
    assert len(out) > 0 and out.t.min() >= 1000 and out.t.max() < 61_000
    # noise starts with the stream: none before its first slice
    late, _ = run(params, silence(250_000, 400_000))
    assert late.t.min() >= 250_000


def test_flow_packets_come_out_as_events():
    from evchain.testing.synthetic import expansion_stream

    packets, _ = expansion_stream()
    out, _ = run({"shot_rate_hz": 5.0}, packets[:2])
    assert type(out) is EventPacket and len(out) > sum(len(p) for p in packets[:2])


@pytest.mark.parametrize("bad", [{"leak_rate_hz": -1}, {"hot_pixel_fraction": 0.5},
                                 {"hot_pixel_rate_hz": 0}, {"shot_rate_hz": 1e6},
                                 {"leak_jitter": 2}, {"leak_spread_decades": 1}])
def test_bad_parameters_are_refused(bad):
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        SensorNoise.Params(**bad)
