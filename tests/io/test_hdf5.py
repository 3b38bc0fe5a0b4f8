import numpy as np
import pytest

from evchain.core.chain import run_pipeline
from evchain.core.config import pipeline_from_text
from evchain.core.filter import Filter
from evchain.core.packets import EventPacket
from evchain.core.registry import make_registry
from evchain.errors import FilterError
from evchain.hookspecs import hookimpl
from evchain.testing.contract import check_source
from evchain.testing.synthetic import random_events

h5py = pytest.importorskip("h5py")


def write_file(path, ev, width=64, height=48, p01=False):
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g.attrs.update({"width": width, "height": height})
        for c in ("x", "y", "t"):
            g[c] = getattr(ev, c)
        g["p"] = (ev.p > 0).astype(np.uint8) if p01 else ev.p


@pytest.mark.parametrize("block_events", [1 << 20, 1000])
def test_round_trip_through_pipeline(tmp_path, monkeypatch, block_events):
    """Identical events back, whether the writer appends once at the end or in many blocks."""
    monkeypatch.setattr("evchain.io.hdf5.WRITE_BLOCK_EVENTS", block_events)
    ev = random_events(5000, t_start=0, t_end=95_000, seed=1)
    write_file(tmp_path / "in.h5", ev, p01=True)
    registry = make_registry()
    text = (f"chain:\n  - use: hdf5\n    path: {tmp_path / 'in.h5'}\n    packet_us: 7000\n"
            "  - use: hdf5_writer\n    path: copy.h5\n")
    run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path / "run")
    with h5py.File(tmp_path / "run" / "copy.h5") as f:
        for c in ("x", "y", "t", "p"):
            assert np.array_equal(f["events"][c][:], getattr(ev, c)), c
        assert f["events"].attrs["width"] == 64


def test_failed_run_leaves_only_partial(tmp_path):
    ev = random_events(500, t_start=0, t_end=30_000, seed=2)
    write_file(tmp_path / "in.h5", ev)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "copy.h5").write_bytes(b"stale output of an earlier run")
    registry = make_registry(discover=False, plugins=(_FailPlugin(),))
    text = (f"chain:\n  - use: hdf5\n    path: {tmp_path / 'in.h5'}\n    packet_us: 7000\n"
            "  - use: hdf5_writer\n    path: copy.h5\n  - use: toy_fail\n")
    with pytest.raises(FilterError, match="disk on fire"):
        run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path / "run")
    assert not (tmp_path / "run" / "copy.h5").exists()
    assert (tmp_path / "run" / "copy.h5.partial").exists()


class _Fail(Filter):
    """Fails on the second packet."""

    name = "toy_fail"
    consumes = EventPacket

    def reset(self):
        self.seen = 0

    def process(self, packet):
        self.seen += 1
        if self.seen == 2:
            raise RuntimeError("disk on fire")
        return packet


class _FailPlugin:
    @hookimpl
    def evchain_filters(self):
        return [_Fail]


def test_source_contract_and_slices(tmp_path):
    ev = random_events(3000, t_start=100, t_end=50_000, seed=2)
    write_file(tmp_path / "in.h5", ev)
    packets = check_source(registry_cls("hdf5"), {"path": str(tmp_path / "in.h5"),
                                                  "packet_us": 5000}, out_dir=tmp_path,
                           max_packets=1000)
    whole = EventPacket.concat(packets)
    assert np.array_equal(whole.t, ev.t) and np.array_equal(whole.p, ev.p)


def registry_cls(name):
    return make_registry().get(name)


@pytest.mark.parametrize("mutate, pattern", [
    (lambda g: g.__delitem__("p"), "lacks datasets \\['p'\\]"),
    (lambda g: g.attrs.__delitem__("width"), "no width/height"),
    (lambda g: (g.__delitem__("x"), g.create_dataset("x", data=np.zeros((10, 2), np.uint16))),
     r"datasets events/x must be 1-D \(one value per event\), got shapes x \(10, 2\)"),
])
def test_bad_files(tmp_path, mutate, pattern):
    ev = random_events(10, seed=3)
    path = tmp_path / "bad.h5"
    write_file(path, ev)
    with h5py.File(path, "a") as f:
        mutate(f["events"])
    registry = make_registry()
    text = f"chain:\n  - use: hdf5\n    path: {path}\n"
    with pytest.raises(FilterError, match=f"{path}: .*{pattern}"):
        run_pipeline(pipeline_from_text(text, "p.yaml", registry), registry, tmp_path / "r")


def test_not_hdf5_and_outside_sensor(tmp_path):
    (tmp_path / "x.h5").write_text("hello")
    registry = make_registry()
    with pytest.raises(FilterError, match="not an HDF5 file"):
        run_pipeline(pipeline_from_text(f"chain:\n  - use: hdf5\n    path: {tmp_path / 'x.h5'}\n",
                                        "p.yaml", registry), registry, tmp_path / "r")
    ev = random_events(10, seed=3)
    write_file(tmp_path / "small.h5", ev, width=8, height=8)
    with pytest.raises(FilterError, match="outside the 8x8 sensor"):
        run_pipeline(pipeline_from_text(
            f"chain:\n  - use: hdf5\n    path: {tmp_path / 'small.h5'}\n", "p.yaml", registry),
            registry, tmp_path / "r2")
