"""Pictures researchers expect: flow arrows, the colour wheel, the FOE legend, TTC labels."""

from __future__ import annotations

import imageio.v2 as iio
import matplotlib.colors
import numpy as np
import pytest

from evchain.core.packets import EventPacket, FlowPacket, Geometry
from evchain.core.series import TTC, TTC_CLUSTERS
from evchain.filters.video import Video
from evchain.report.flow_image import flow_image
from evchain.report.overlay import (
    draw_legend,
    overlaps,
    place_labels,
    text_size,
    wheel_box,
)
from evchain.report.render import RED, YELLOW
from evchain.report.video_frame import OBSTACLE, compose
from evchain.testing.contract import make_context, run_filter
from evchain.testing.synthetic import expansion_stream

G = Geometry(64, 48)


def flow_block(x0, x1, y0, y1, vx, vy, t=0):
    ys, xs = np.mgrid[y0:y1, x0:x1]
    n = xs.size
    return FlowPacket(geometry=G, t_start=t, t_end=t + 1000, x=xs.ravel().astype(np.uint16),
                      y=ys.ravel().astype(np.uint16), t=np.full(n, t, np.int64),
                      p=np.ones(n, np.int8), vx=np.full(n, vx, np.float32),
                      vy=np.full(n, vy, np.float32))


def white(img):
    return (img == 255).all(axis=-1)


def hue_deg(rgb):
    return matplotlib.colors.rgb_to_hsv(np.asarray(rgb, float) / 255)[0] * 360


def wheel_hues_ok(img):
    """The wheel's hue at 8 angles (0 = right, 90 = down) is the angle, within 8 degrees."""
    x0, y0, x1, y1 = wheel_box(img.shape)
    cx, cy, r = (x0 + x1 - 1) / 2, (y0 + y1 - 1) / 2, (x1 - x0 - 1) / 2
    for angle in range(0, 360, 45):
        a = np.radians(angle)
        px = img[int(round(cy + 0.7 * r * np.sin(a))), int(round(cx + 0.7 * r * np.cos(a)))]
        assert abs((hue_deg(px) - angle + 180) % 360 - 180) < 8, (angle, px)
    return True


def test_flow_picture_has_the_wheel_in_its_corner():
    p = flow_block(2, 6, 2, 6, 10.0, 0.0)
    img = flow_image(p.x, p.y, p.vx, p.vy, G.width, G.height, scale=3, arrows_every_px=0)
    assert wheel_hues_ok(img)


@pytest.mark.parametrize("vx, vy", [(100.0, 0.0), (0.0, 100.0), (-70.0, -70.0)])
def test_arrows_drawn_where_flow_is_pointing_along_it(vx, vy):
    """Flow in one 8x8 block only (cells of 16 output px at scale 2): white arrow pixels lie in
    that block's cell, the shaft crosses its centre and the head lies ahead of the centre."""
    p = flow_block(8, 16, 16, 24, vx, vy)
    img = flow_image(p.x, p.y, p.vx, p.vy, G.width, G.height, scale=2, wheel=False)
    ys, xs = np.nonzero(white(img))
    assert len(xs) > 10
    assert xs.min() >= 16 and xs.max() < 32 and ys.min() >= 32 and ys.max() < 48
    cx, cy = 23.5, 39.5  # the cell's centre in output pixels
    ahead = (xs - cx) * vx + (ys - cy) * vy
    assert ahead.max() > 5 and ahead.min() < -5  # a shaft through the centre
    ux, uy = np.array([vx, vy]) / np.hypot(vx, vy)
    off_axis = np.abs((xs - cx) * uy - (ys - cy) * ux) >= 1.5
    assert off_axis.any() and (ahead[off_axis] > 0).all()  # the head at the tip
    none = flow_image(p.x, p.y, p.vx, p.vy, G.width, G.height, scale=2, wheel=False,
                      arrows_every_px=0)
    assert not white(none).any()


def test_arrow_length_follows_speed():
    fast = flow_block(0, 8, 0, 8, 200.0, 0.0)
    slow = flow_block(32, 40, 0, 8, 50.0, 0.0)
    both = FlowPacket.concat([fast, slow])
    img = flow_image(both.x, both.y, both.vx, both.vy, G.width, G.height, scale=2, wheel=False)
    row = white(img)[7]  # the shafts' row (cell centre y = 7.5)
    assert row[:16].sum() > 2 * row[64:80].sum() > 0


def test_flow_video_frame_has_arrows_and_wheel():
    p = flow_block(8, 16, 16, 24, 100.0, 0.0)
    img, _ = compose(p, 3)
    assert wheel_hues_ok(img)
    assert white(img[48:72, 24:48]).any()  # the arrow in the flow block's cell
    plain, _ = compose(EventPacket(geometry=G, t_start=0, t_end=1000, x=p.x, y=p.y, t=p.t,
                                   p=p.p), 3)
    box = wheel_box(plain.shape)
    assert not plain[box[1]:box[3], box[0]:box[2]].any()  # no wheel on event frames


def test_foe_legend_names_estimate_and_truth():
    ev = EventPacket.empty(G, 0, 1000)
    img, _ = compose(ev, 2, foe=(20.0, 30.0), foe_true=(10.0, 40.0))
    _, box = draw_legend(np.zeros_like(img), [(YELLOW, "FOE estimate"), (RED, "FOE truth")])
    x0, y0, x1, y1 = box
    assert x1 == img.shape[1] - 2 and y0 == 2  # top-right corner
    region = img[y0:y1, x0:x1]
    assert (region == YELLOW).all(axis=-1).sum() >= 7 and (region == RED).all(axis=-1).sum() >= 7
    assert (region.min(axis=-1) > 200).sum() > 20  # the names, in white
    # the markers themselves are where the FOEs are (scale 2), outside the legend
    assert (img[60, 40] == YELLOW).all() and (img[80, 20] == RED).all()
    only, _ = compose(ev, 2, foe=(20.0, 30.0))
    assert not (only[y0:y1, x0:x1] == RED).all(axis=-1).any()


def clusters(points, tau=1.5):
    cl = np.zeros(len(points), TTC_CLUSTERS.dtype)
    cl["t"] = 500
    cl["cluster"] = np.arange(len(points))
    cl["x"], cl["y"] = np.array(points, float).T
    cl["size_px"] = 2.0
    cl["tau_s"] = tau + np.arange(len(points)) * 0.37
    cl["support"] = np.arange(len(points), 0, -1)
    return cl


def test_ttc_labels_do_not_overlap():
    """Eight clusters within a few pixels: every label that is drawn has a box of its own,
    inside the frame, clear of the header, legend and wheel, and the obstacle's comes first."""
    ev = flow_block(20, 40, 20, 30, 50.0, 0.0)
    cl = clusters([(30, 25), (31, 25), (30, 26), (33, 24), (29, 27), (32, 27), (31, 23),
                   (34, 26)])
    header = "   0.001 s  TTC 1.50 s"
    img, boxes = compose(ev, 3, foe=(30.0, 20.0), foe_true=(31.0, 20.0), header=header,
                         clusters=cl, obstacle=3)
    placed = [b for b in boxes if b is not None]
    assert len(placed) >= 5 and boxes[0] is not None  # the obstacle (cluster 3) first
    for i, a in enumerate(placed):
        assert 0 <= a[0] and 0 <= a[1] and a[2] <= img.shape[1] and a[3] <= img.shape[0]
        for b in placed[i + 1:]:
            assert not overlaps(a, b)
    _, legend = draw_legend(np.zeros_like(img), [(YELLOW, "FOE estimate"), (RED, "FOE truth")])
    w, h = text_size(header)
    for other in (legend, wheel_box(img.shape), (2, 2, 2 + w, 2 + h)):
        assert not any(overlaps(b, other) for b in placed)
    x0, y0, x1, y1 = boxes[0]  # the obstacle's label is written in orange
    assert (np.abs(img[y0:y1, x0:x1].astype(int) - OBSTACLE).max(axis=-1) < 60).sum() > 5


def test_place_labels_gives_up_rather_than_overlap():
    boxes = place_labels([(50, 50)] * 12, [(20, 10)] * 12, 100, 100)
    placed = [b for b in boxes if b is not None]
    assert len(placed) == 6 and boxes[6:] == [None] * 6  # two columns of three rows
    assert all(not overlaps(a, b) for i, a in enumerate(placed) for b in placed[i + 1:])
    edge = place_labels([(98, 2)], [(20, 10)], 100, 100)[0]
    assert edge is not None and edge[2] <= 100 and edge[1] >= 0


def test_video_draws_the_clusters_of_the_series(tmp_path):
    packets, truth = expansion_stream(n_packets=2, packet_us=25_000, foe_series=True)
    out = []
    for p in packets:
        cl = clusters([(40, 70), (90, 70)])
        cl["t"] = p.t_start
        ttc = TTC.array(t=[p.t_start], tau_s=[1.5], cluster=[1], x=[90.0], y=[70.0])
        out.append(p.with_series("ttc_clusters", cl).with_series("ttc", ttc))
    f = Video()
    f.setup(Video.Params(path="v.gif", frame_us=25_000, scale=2),
            make_context(out[0].geometry, truth, tmp_path))
    run_filter(f, out)
    f.close()
    frame = np.asarray(iio.mimread(tmp_path / "v.gif")[0])[..., :3].astype(int)
    orange = np.abs(frame - OBSTACLE).max(axis=-1) < 40
    assert orange[130:152, 170:200].any()  # the obstacle's square around (90, 70) at scale 2


def test_video_drops_clusters_when_no_tick_comes(tmp_path):
    """Clusters of a tick stay on screen for 100 ms, then go when no newer tick comes."""
    packets, truth = expansion_stream(n_packets=6, packet_us=25_000, foe_series=True)
    cl = clusters([(90, 70)])
    cl["t"] = packets[0].t_start
    ttc = TTC.array(t=[packets[0].t_start], tau_s=[1.5], cluster=[0], x=[90.0], y=[70.0])
    packets[0] = packets[0].with_series("ttc_clusters", cl).with_series("ttc", ttc)
    f = Video()
    f.setup(Video.Params(path="v.gif", frame_us=25_000, scale=2),
            make_context(packets[0].geometry, truth, tmp_path))
    run_filter(f, packets)
    f.close()
    frames = [np.asarray(fr)[..., :3].astype(int) for fr in iio.mimread(tmp_path / "v.gif")]
    shown = [(np.abs(fr[120:160, 160:210] - OBSTACLE).max(axis=-1) < 40).any() for fr in frames]
    assert shown == [True, True, True, True, False, False]
