"""The filter contract over every registered filter, with standard synthetic input.

Filters that need parameters to run (files, ground truth) get them from ``PARAMS``; a new filter
that fails here with defaults needs an entry (or a fix).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evchain.core.packets import EventPacket, FlowPacket, FramePacket, Geometry, Packet
from evchain.core.registry import make_registry
from evchain.core.series import FOE
from evchain.testing.contract import check_filter, check_source, recut
from evchain.testing.synthetic import (
    expansion_stream,
    moving_edge_events,
    random_events,
    textured_frames,
)

REGISTRY = make_registry()
BUILTIN = sorted(n for n, i in REGISTRY.filters.items() if i.distribution == "evchain")

# Per-filter parameters for the contract run ({} = defaults). Callables get tmp_path.
PARAMS = {
    "aedat": {"path": str(Path(__file__).resolve().parents[1] / "data" /
                          "moving_edge_davis240.aedat")},
    "aedat_writer": lambda tmp: {"path": str(tmp / "out.aedat")},
    "aps": {"rate_hz": 500, "exposure_us": 1500, "read_noise_e": 10.0},
    # the standard stream has no still stretch to take the gyro bias from
    "imu_truth": {"gyro_bias_dps": [0.0, 0.0, 0.0]},
    "scene": {"width": 64, "height": 48, "supersample": 1, "duration_s": 0.04},
    # every noise process on (off by default: the contract would see the identity)
    "sensor_noise": {"leak_rate_hz": 20.0, "shot_rate_hz": 10.0, "hot_pixel_fraction": 0.01,
                     "hot_pixel_rate_hz": 500.0},
}


def event_stream() -> list[EventPacket]:
    g = Geometry(64, 48, f=60.0)
    edge = moving_edge_events(400.0, 150.0, g, duration_us=150_000)
    noise = random_events(300, g, 0, 150_000, seed=3)
    merged = EventPacket(geometry=g, t_start=0, t_end=150_000,
                         **{c: np.concatenate([getattr(edge, c), getattr(noise, c)])
                            for c in EventPacket.columns})
    merged = merged.select(np.argsort(merged.t, kind="stable"))
    return recut([merged], [40_000, 90_000])


def frame_stream() -> list[FramePacket]:
    g = Geometry(48, 32, f=40.0)
    return [textured_frames(8, g, dt_us=1000, t0_us=0, seed=1).replace(t_end=8000),
            textured_frames(8, g, dt_us=1000, t0_us=8000, seed=1).replace(t_start=8000,
                                                                         t_end=16000)]


# filters of optional extras: the module they need
NEEDS_MODULE = {"frame_flow": "cv2"}


def params_for(name, tmp_path):
    p = PARAMS.get(name, {})
    return p(tmp_path) if callable(p) else p


@pytest.mark.parametrize("name", BUILTIN)
def test_contract(name, tmp_path):
    cls = REGISTRY.get(name)
    params = params_for(name, tmp_path)
    if name in NEEDS_MODULE:
        pytest.importorskip(NEEDS_MODULE[name])
    if cls.is_source():
        if name in SOURCE_SKIP:
            pytest.skip(SOURCE_SKIP[name])
        check_source(cls, params, out_dir=tmp_path, max_packets=5)
        return
    # flow input, and the truth every scorer needs; stages that read the FOE get the true one
    reads = (*cls.needs_series, *cls.optional_series)
    packets, truth = expansion_stream(foe_series=FOE in reads)
    if cls.consumes is FramePacket:
        packets = frame_stream()
    elif cls.consumes is not FlowPacket and cls.consumes is not Packet:
        packets = event_stream()
    check_filter(cls, params, with_series(packets, reads), truth=truth, out_dir=tmp_path)


def with_series(packets: list[Packet], series) -> list[Packet]:
    """``packets`` carrying each of ``series``: the ones they lack get an entry of zeros (t =
    the packet's start) per packet, so that the contract sees every series a filter reads."""
    out = []
    for p in packets:
        for s in series:
            if s.name not in p.series:
                p = p.with_series(s.name, s.array(t=[p.t_start]))
        out.append(p)
    return out


# Sources that cannot run without a file are covered by their own tests.
SOURCE_SKIP = {
    "frames": "needs a file; covered in tests/io",
    "hdf5": "needs a file; covered in tests/io/test_hdf5.py",
    "scene_events": "needs a simulator run's file; covered in tests/sim/test_scene_events.py",
}
