"""The side-by-side runner of other emulators (evchain.benchmarks.emulator_peers), with fake
peers: the real ones (esim_py, v2e) are not dependencies, and the tests do not use them even
where they are installed."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from evchain.benchmarks import emulator_peers as ep
from evchain.benchmarks.emulator import _run, bar_frames, textured_scene


def test_absent_peers_give_no_rows_and_say_how_to_get_them(monkeypatch, capsys):
    monkeypatch.setattr(ep, "FINDERS", [ep.find_esim, ep.find_v2e])
    monkeypatch.setitem(sys.modules, "esim_py", None)          # import fails
    monkeypatch.setitem(sys.modules, "v2ecore", None)
    assert ep.WORKLOADS["emulator-peer-bar"](True) == []
    err = capsys.readouterr().err
    assert "emulator-peer-bar: ESIM's core (esim_py) is not importable" in err
    assert ("emulator-peer-bar: v2e's emulator (v2ecore.emulator with torch) is not "
            "importable") in err
    assert err.count('docs/explanation/emulator.md, "Peers"') == 2


class OwnEmulator:
    """A fake peer: evchain's emulator itself, float times (so its error is evchain's)."""

    name = "own"

    def run(self, frames, times_us):
        outs, tf = _run(frames, times_us, {"threshold_on": 0.2, "threshold_off": 0.2,
                                           "eps": 1e-3}, record=True)
        x = np.concatenate([o.x for o in outs])
        y = np.concatenate([o.y for o in outs])
        p = np.concatenate([o.p for o in outs])
        return np.column_stack([x, y, tf, p]).astype(np.float64)

    def events(self, output):
        return output


def test_fake_peer_rows_on_the_bar(monkeypatch):
    from evchain.report.timing import timing_errors
    from evchain.sim.bar import BarTruth

    monkeypatch.setattr(ep, "FINDERS", [lambda: OwnEmulator(), lambda: "absent"])
    monkeypatch.setitem(ep.FRAMES, "bar", {320: (0, 40)})
    (row,) = ep.WORKLOADS["emulator-peer-bar"](True)
    assert row.workload == "emulator-peer-own-bar" and row.stage == "own"
    x = row.extra
    assert x["frames"] == 40 and row.unit == "frames/s" and row.throughput > 0
    assert x["speedup"] == pytest.approx(x["ms_per_frame"] / x["evchain_ms_per_frame"])
    bar_, frames, times = bar_frames(40)
    truth = BarTruth(bar_).crossing_times(0.2, 0.2, 1e-3, times[0], times[-1])
    ev = OwnEmulator().run(frames, times)
    want = timing_errors(ev[:, 0], ev[:, 1], ev[:, 3], ev[:, 2], truth, 320)
    assert row.error == want["median_abs_dt_us"] < 1.0
    assert x["count_diff"] == 0 and x["events"] == len(ev) > 1000


def test_fake_peer_on_a_texture_has_no_error(monkeypatch):
    monkeypatch.setattr(ep, "FINDERS", [lambda: OwnEmulator()])
    monkeypatch.setitem(ep.FRAMES, "textured", {640: (0, 12)})
    (row,) = ep.WORKLOADS["emulator-peer-textured-640x480"](True)
    assert row.workload == "emulator-peer-own-textured-640x480"
    assert row.error is None and row.extra["events"] > 0 and "640x480, 12 frames" in row.data


def test_esim_adapter(monkeypatch):
    calls = {}

    class EventSimulator:
        def __init__(self, *args):
            calls["init"] = args

        def generateFromFloatFrames(self, frames, timestamps):   # noqa: N802 (its name)
            calls["frames"], calls["timestamps"] = frames, timestamps
            return np.array([[3.0, 1.0, 0.0015, 1.0], [4.0, 2.0, 0.002, -1.0]])

    monkeypatch.setitem(sys.modules, "esim_py", types.SimpleNamespace(
        EventSimulator=EventSimulator))
    peer = ep.find_esim()
    assert isinstance(peer, ep.EsimPeer)
    frames = np.full((3, 2, 5), 0.5, np.float64)
    ev = peer.events(peer.run(frames, np.array([0, 1000, 2000])))
    assert calls["init"] == (0.2, 0.2, 0.0, 1e-3, True)
    assert calls["frames"].dtype == np.float32 and calls["frames"].shape == (3, 2, 5)
    assert calls["timestamps"] == [0.0, 0.001, 0.002]
    np.testing.assert_allclose(ev, [[3, 1, 1500, 1], [4, 2, 2000, -1]])

    del EventSimulator.generateFromFloatFrames        # the stock module: files only
    assert "generateFromFloatFrames" in ep.find_esim()


def test_v2e_adapter(monkeypatch):
    made = {}

    class EventEmulator:
        def __init__(self, **kw):
            made["kw"] = kw
            made["frames"] = []

        def generate_events(self, frame, t):
            made["frames"].append((frame, t))
            if len(made["frames"]) == 1:
                return None                            # the first frame initialises
            return np.array([[t, 7.0, 1.0, 1.0], [t, 8.0, 0.0, -1.0]])

    threads = []
    monkeypatch.setitem(sys.modules, "torch", types.SimpleNamespace(
        set_num_threads=threads.append))
    monkeypatch.setitem(sys.modules, "v2ecore", types.ModuleType("v2ecore"))
    monkeypatch.setitem(sys.modules, "v2ecore.emulator", types.SimpleNamespace(
        EventEmulator=EventEmulator))
    peer = ep.find_v2e()
    assert isinstance(peer, ep.V2ePeer)
    frames, times = textured_scene(3, width=8, height=4)
    ev = peer.events(peer.run(frames, times))
    assert threads == [1]
    kw = made["kw"]
    assert kw["hdr"] and kw["device"] == "cpu" and kw["pos_thres"] == kw["neg_thres"] == 0.2
    assert kw["cutoff_hz"] == kw["leak_rate_hz"] == kw["shot_noise_rate_hz"] == 0
    assert kw["refractory_period_s"] == kw["sigma_thres"] == 0
    np.testing.assert_allclose(made["frames"][1][0], np.log(frames[1].astype(np.float64) + 1e-3),
                               rtol=1e-6)
    assert [t for _, t in made["frames"]] == [0.0, 0.001, 0.002]
    np.testing.assert_allclose(ev, [[7, 1, 1000, 1], [8, 0, 1000, -1],
                                    [7, 1, 2000, 1], [8, 0, 2000, -1]])
