"""flow_image: the picture's colours, windows, files, and re-rendering from saved data."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest
from pydantic import ValidationError

from evchain.core.filter import Context
from evchain.core.packets import FlowPacket, Geometry
from evchain.filters.flow_image import FlowImage
from evchain.report.flow_image import flow_image, flow_image_from_file, load_flow
from evchain.testing.contract import check_filter, recut
from evchain.testing.synthetic import expansion_stream

G = Geometry(40, 30)


def flow_packet(t_start=0, t_end=1000):
    # four pixels: right, down, left, up (image coordinates, y down)
    x = np.array([5, 10, 15, 20], np.uint16)
    y = np.array([5, 5, 5, 5], np.uint16)
    t = np.array([100, 200, 300, 400], np.int64)
    vx = np.array([10, 0, -10, 0], np.float32)
    vy = np.array([0, 10, 0, -10], np.float32)
    return FlowPacket(geometry=G, t_start=t_start, t_end=t_end, x=x, y=y, t=t,
                      p=np.ones(4, np.int8), vx=vx, vy=vy)


def test_direction_is_hue():
    p = flow_packet()
    img = flow_image(p.x, p.y, p.vx, p.vy, G.width, G.height, wheel=False, arrows_every_px=0)
    assert img.shape == (30, 40, 3) and img.dtype == np.uint8
    assert tuple(img[5, 5]) == (255, 0, 0)        # right: hue 0, red
    assert tuple(img[5, 15]) == (0, 255, 255)     # left: hue 180, cyan
    down, up = img[5, 10], img[5, 20]             # 90 deg: yellow-green, 270: violet
    assert down[1] == 255 and down[2] == 0 and up[2] == 255 and up[1] == 0
    assert img.sum() == img[5, [5, 10, 15, 20]].sum()   # nothing else drawn
    # the mean vector decides a pixel hit twice: right + down -> 45 deg (orange-yellow)
    two = flow_image(np.array([3, 3]), np.array([3, 3]), np.array([10.0, 0]),
                     np.array([0, 10.0]), 8, 8, wheel=False, arrows_every_px=0)
    assert two[3, 3, 0] == 255 and 0 < two[3, 3, 1] < 255 and two[3, 3, 2] == 0


def test_window_and_scale_and_wheel():
    p = flow_packet()
    img = flow_image(p.x, p.y, p.vx, p.vy, G.width, G.height, t=p.t, t_window_us=(150, 350),
                     scale=3, wheel=False)
    assert img.shape == (90, 120, 3)
    assert not img[15:18, 15:18].any() and not img[15:18, 60:63].any()  # t=100, t=400 outside
    assert img[15:18, 30:33].any() and img[15:18, 45:48].any()
    with_wheel = flow_image(p.x, p.y, p.vx, p.vy, G.width, G.height, scale=3)
    assert with_wheel[-20:, -20:].any()  # legend in the bottom-right corner


def run_sink(params, packets, tmp_path):
    f = FlowImage()
    f.setup(FlowImage.Params(**params), Context(out_dir=tmp_path, geometry=G))
    for p in packets:
        assert f.process(p) is p
    f.flush()
    f.close()


def test_sink_writes_png_atomically(tmp_path):
    packets = recut([flow_packet(0, 1000)], [250, 251, 600])
    run_sink({"path": "pics/flow.png", "t_window_us": [150, 350], "scale": 1, "wheel": False},
             packets, tmp_path)
    out = tmp_path / "pics" / "flow.png"
    assert out.exists() and not list(tmp_path.rglob("*.partial"))
    img = iio.imread(out)
    expect = flow_image(*(getattr(flow_packet(), c) for c in ("x", "y", "vx", "vy")),
                        G.width, G.height, t=flow_packet().t, t_window_us=(150, 350),
                        wheel=False)
    np.testing.assert_array_equal(img, expect)


def test_sink_times_and_saved_data_rerender(tmp_path):
    packets = recut([flow_packet(0, 1000)], [333])
    run_sink({"times_us": [250, 450], "duration_us": 100, "save_npz": "flow.npz"}, packets,
             tmp_path)
    a, b = tmp_path / "flow_250us.png", tmp_path / "flow_450us.png"
    assert a.exists() and b.exists()
    assert iio.imread(a)[10:12, 20:22].any()   # t=200 at (10, 5), scale 2
    assert not iio.imread(a)[10:12, 40:42].any()
    d = load_flow(tmp_path / "flow.npz")
    assert sorted(d["t"].tolist()) == [200, 400] and d["width"] == 40
    again = flow_image_from_file(tmp_path / "flow.npz", tmp_path / "again.png",
                                 t_window_us=(150, 250))
    np.testing.assert_array_equal(iio.imread(again), iio.imread(a))


def test_params_are_checked():
    with pytest.raises(ValidationError):
        FlowImage.Params(t_window_us=[10, 20], times_us=[5])
    with pytest.raises(ValidationError):
        FlowImage.Params(t_window_us=[20, 10])
    with pytest.raises(ValidationError):
        FlowImage.Params(path="flow.jpg")


def test_contract(tmp_path):
    packets, truth = expansion_stream()
    check_filter(FlowImage, {"path": "f.png"}, packets, truth=truth, out_dir=tmp_path)
    assert (tmp_path / "f.png").exists() or list(tmp_path.rglob("f.png"))
