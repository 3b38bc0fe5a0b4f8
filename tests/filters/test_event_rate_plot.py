"""Sink ``event_rate_plot``: bin counts, series entries inside their packets' slices."""

from __future__ import annotations

import numpy as np

from evchain.core.packets import EventPacket, Geometry
from evchain.filters.event_rate import EventRatePlot
from evchain.testing.contract import check_filter, make_context, run_filter

G = Geometry(16, 8)


def stream(cuts, t_end=95_001, seed=0, n=400):
    """Random events (a third at column 3), cut into packets at ``cuts``."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, t_end, n)).astype(np.int64)
    t[-1] = t_end - 1                              # an event in the very last µs
    x = np.where(rng.random(n) < 0.35, 3, rng.integers(0, 16, n)).astype(np.uint16)
    y = rng.integers(0, 8, n).astype(np.uint16)
    p = np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)
    whole = EventPacket(geometry=G, t_start=0, t_end=t_end, x=x, y=y, t=t, p=p)
    edges = [0, *cuts, t_end]
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        m = (t >= a) & (t < b)
        out.append(whole.select(m).replace(t_start=a, t_end=b))
    return whole, out


def run(packets, tmp_path, bin_us=10_000):
    f = EventRatePlot()
    f.setup(EventRatePlot.Params(column=3, bin_us=bin_us, path="rate.png"),
            make_context(G, None, tmp_path, 0))
    return run_filter(f, packets)


def test_series_entries_inside_their_slices_and_counts(tmp_path):
    whole, packets = stream([10_000, 20_000, 33_333, 33_334, 60_000, 95_000])
    outs = run(packets, tmp_path)
    for o in outs:
        s = o.series.get("event_rate", np.zeros(0, [("t", "i8")]))
        assert np.all((s["t"] >= o.t_start) & (s["t"] < o.t_end)), (o.t_start, o.t_end, s["t"])
    # the last partial bin [90000, 95001) is the flush packet's, inside its slice
    last = outs[-1]
    assert last.t_end == 95_001 and last.t_start == 95_000
    assert list(last.series["event_rate"]["t"]) == [95_000]
    ser = EventPacket.concat(outs).series["event_rate"]
    assert list(ser["t_bin_start"]) == list(range(0, 100_000, 10_000))
    col = whole.x == 3
    for e in ser:
        m = col & (whole.t >= e["t_bin_start"]) & (whole.t < e["t_bin_end"])
        assert e["on"] == int((whole.p[m] > 0).sum()) and e["off"] == int((whole.p[m] < 0).sum())
        span = e["t_bin_end"] - e["t_bin_start"]
        assert np.isclose(e["rate_eps"], m.sum() * 1e6 / span)
    assert ser["t_bin_end"][-1] == 95_001
    # events pass through unchanged (slices lag by 1 µs)
    ev = EventPacket.concat(outs)
    assert np.array_equal(ev.t, whole.t) and np.array_equal(ev.x, whole.x)
    assert (tmp_path / "rate.png").stat().st_size > 0


def test_bin_ending_at_packet_end_and_upstream_series(tmp_path):
    whole, packets = stream([20_000, 40_000], t_end=60_000)
    up = np.array([(19_999, 1.0), (20_000, 2.0), (59_999, 3.0)], [("t", "i8"), ("v", "f8")])
    packets = [p.with_series("up", up[(up["t"] >= p.t_start) & (up["t"] < p.t_end)])
               for p in packets]
    outs = run(packets, tmp_path)
    for o in outs:
        for s in o.series.values():
            assert np.all((s["t"] >= o.t_start) & (s["t"] < o.t_end))
    whole_out = EventPacket.concat(outs)
    assert list(whole_out.series["up"]["v"]) == [1.0, 2.0, 3.0]
    # a stream ending on a bin edge has no partial bin
    assert list(whole_out.series["event_rate"]["t"]) == [9_999, 19_999, 29_999, 39_999,
                                                         49_999, 59_999]


def test_contract_with_cuts(tmp_path):
    _, packets = stream([25_000, 25_001, 70_000])
    check_filter(EventRatePlot, {"column": 3, "bin_us": 7_000, "path": None}, packets)
