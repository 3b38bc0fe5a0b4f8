"""Geometry, motion field, FOE and TTC ground truth of the scene simulator."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates

from evchain.sim.camera import focal_from_fov
from evchain.sim.drive import Scene
from evchain.sim.truth import OBJECT_GROUND, OBJECT_SKY, SceneTruth
from tests.naive import scene_kernels as N


def test_focal_length_from_fov():
    assert focal_from_fov(240, 35.0) == pytest.approx(380.59, abs=0.01)
    assert focal_from_fov(100, 90.0) == pytest.approx(50.0)
    sc = Scene.from_params(width=320, height=240, fov_deg=35.0)
    g = sc.geometry
    assert (g.f, g.cx, g.cy) == (pytest.approx(380.59, abs=0.01), 159.5, 119.5)


def test_box_corners_project_like_a_pinhole():
    sc = Scene.from_params(scenario="open-field", width=160, height=120, start_m=20.0)
    truth = SceneTruth(sc)
    car = [i for i, lab in enumerate(sc.world.labels) if lab == "car"][0]
    x0, y0, z0, x1, y1, z1 = sc.boxes[car]
    corners = np.array([[x0, y, z] for y in (y0, y1) for z in (z0, z1)])
    t = 0.5
    uv = sc.project(corners, t)
    pos, rot, _, _ = sc.state(t)
    pc = (corners - pos) @ rot                        # camera coordinates
    np.testing.assert_allclose(uv[:, 0], sc.camera.f * pc[:, 0] / pc[:, 2] + sc.camera.cx)
    np.testing.assert_allclose(uv, N.project(corners, t, sc)[0], atol=1e-9)
    # the ray through the projected near-face centre hits that face at its depth
    centre = np.array([[x0, (y0 + y1) / 2, (z0 + z1) / 2]])
    c_uv = sc.project(centre, t)[0]
    depth = truth.depth(c_uv[0], c_uv[1], t * 1e6)
    assert depth == pytest.approx(x0 - pos[0], rel=1e-9)
    # straight-road geometry by hand: camera 1.2 m up, level: ground at row cy + f h / Z
    z = 10.0
    row = sc.camera.cy + sc.camera.f * 1.2 / z
    assert truth.depth(sc.camera.cx, row, 0.0) == pytest.approx(z, rel=1e-9)


def test_object_id_sees_the_car_and_the_sky():
    """A high-rise drive: near its end the ray through the projected centre of the car's rear
    face hits one of the obstacle's boxes at that face's depth; at its start the top centre
    pixel sees the sky over the building closing the street, the bottom row the road."""
    sc = Scene.from_params(scenario="high-rise", width=160, height=120, start_m=120.0,
                           duration_s=7.8)
    truth = SceneTruth(sc)
    assert [sc.world.labels[i] for i in truth.obstacle_ids] == ["car"] * 4
    t = 7.6                                   # the car's rear face 9 m ahead
    u, v = sc.project(sc.world.obstacle_rear[None], t)[0]
    assert 0 <= u < 160 and 0 <= v < 120
    seen = truth.object_id(u, v, t * 1e6)
    assert seen in truth.obstacle_ids and sc.world.labels[seen] == "car"
    pos = sc.state(t)[0]
    assert truth.depth(u, v, t * 1e6) == pytest.approx(sc.world.obstacle_rear[0] - pos[0])
    assert truth.object_id(sc.camera.cx, 0.0, 0.0) == OBJECT_SKY
    assert np.isinf(truth.depth(sc.camera.cx, 0.0, 0.0))
    assert truth.object_id(sc.camera.cx, 119.0, 0.0) == OBJECT_GROUND
    ids = truth.object_id(*np.meshgrid(np.arange(160.0), np.arange(120.0)), t * 1e6)
    assert ids.shape == (120, 160) and np.isin(ids, truth.obstacle_ids).sum() > 100
    no_car = SceneTruth(Scene.from_params(scenario="curves", dynamics="curves"))
    assert no_car.obstacle_ids.dtype == np.int64 and len(no_car.obstacle_ids) == 0


def test_pure_translation_flow_diverges_from_foe():
    sc = Scene.from_params(scenario="high-rise", width=160, height=120, start_m=100.0)
    truth = SceneTruth(sc)
    t_us = 1.5e6
    fx, fy = truth.foe(t_us)
    assert (fx, fy) == (pytest.approx(sc.camera.cx), pytest.approx(sc.camera.cy))
    vx, vy = truth.flow(fx, fy, t_us)
    assert abs(vx) < 1e-9 and abs(vy) < 1e-9
    ys, xs = np.mgrid[0:120:3, 0:160:3].astype(float)
    depth, vx, vy = truth.depth_and_flow(xs, ys, t_us)
    finite = np.isfinite(depth) & ((xs - fx) ** 2 + (ys - fy) ** 2 > 1.0)
    radial = (xs - fx) * vx + (ys - fy) * vy
    assert np.all(radial[finite] > 0)
    # parallel to p - foe: the cross product vanishes
    cross = (xs - fx) * vy - (ys - fy) * vx
    assert np.max(np.abs(cross[finite]) / (np.hypot(vx, vy)[finite] * 1e3 + 1e-9)) < 1e-9
    assert np.all(vx[~np.isfinite(depth)] == 0)     # sky: no rotation, no flow


def test_ttc_falls_one_second_per_second():
    sc = Scene.from_params(scenario="high-rise", speed_mps=20.0)
    truth = SceneTruth(sc)
    t = np.array([0.0, 1.0, 5.0, 13.0]) * 1e6
    tau = truth.ttc(t)
    np.testing.assert_allclose(np.diff(tau), -np.diff(t) * 1e-6, atol=1e-12)
    assert tau[0] == pytest.approx((280.0 + 1.0) / 20.0)
    assert np.isnan(SceneTruth(Scene.from_params(scenario="curves", dynamics="curves")).ttc(0.0))
    still = Scene.from_params(speed_mps=0.0, duration_s=1.0)
    assert np.isnan(SceneTruth(still).ttc(0.5e6))
    assert np.isnan(SceneTruth(still).foe(0.5e6)[0])


def _residuals(sc: Scene, t_s: float, dt_s: float, scales=(1.0,)):
    """Mean |I1 - warp(I0, scale * flow)| for each scale, mean |I1 - I0| and the largest motion,
    away from depth edges (both frames blurred by one pixel first, so that the interpolation of
    the warp does not dominate at sharp edges)."""
    truth = SceneTruth(sc)
    f0 = gaussian_filter(sc.render(t_s)[0].astype(float), 1.0)
    f1 = gaussian_filter(sc.render(t_s + dt_s)[0].astype(float), 1.0)
    h, w = f0.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    depth, vx, vy = truth.depth_and_flow(xs, ys, (t_s + dt_s) * 1e6)
    inv = np.where(np.isfinite(depth), 1.0 / depth, 0.0)
    edge = np.zeros_like(inv, bool)
    for dy in range(-3, 4):
        for dx in range(-3, 4):
            sh = np.roll(np.roll(inv, dy, 0), dx, 1)
            edge |= np.abs(sh - inv) > 0.05 * np.maximum(inv, sh) + 1e-3
    keep = ~edge
    keep[:6], keep[-6:], keep[:, :6], keep[:, -6:] = False, False, False, False
    motion = np.hypot(vx, vy)[keep].max() * dt_s
    warps = [np.abs(f1 - map_coordinates(f0, [ys - s * vy * dt_s, xs - s * vx * dt_s], order=3,
                                          mode="nearest"))[keep].mean() for s in scales]
    return warps, np.abs(f1 - f0)[keep].mean(), motion


@pytest.mark.parametrize("kw,t_s", [
    (dict(scenario="high-rise", start_m=120.0), 0.5),
    (dict(scenario="high-rise", dynamics="pitch", pitch_amplitude_deg=3.0,
          pitch_first_shift_s=0.2), 0.25),
    (dict(scenario="curves", dynamics="curves", start_m=70.0), 0.5),
])
def test_flow_warp_predicts_next_frame(kw, t_s):
    sc = Scene.from_params(width=128, height=96, supersample=2, **kw)
    # 40 ms: a few pixels of motion, well above the floor set by texture aliasing
    (warp, warp_neg, warp_half), still, motion = _residuals(sc, t_s, 4e-2, (1.0, -1.0, 0.5))
    assert 1.5 < motion < 8.0
    assert warp < 0.6 * still, (warp, still)
    # the wrong sign or half the flow predict worse
    assert warp < 0.8 * warp_half and warp < 0.5 * warp_neg


def test_yaw_and_pitch_present():
    pitch = Scene.from_params(dynamics="pitch", pitch_amplitude_deg=2.0, pitch_first_shift_s=0.1)
    _, _, _, wc = pitch.state(0.2)
    assert abs(wc[0]) > 0.01 and abs(wc[1]) < 1e-12      # pitch rate about camera X
    curves = Scene.from_params(scenario="curves", dynamics="curves", start_m=70.0)
    _, _, _, wc = curves.state(0.1)
    assert wc[1] == pytest.approx(-20.0 / 40.0)          # left turn: yaw about -Y (up)


def _rotational_flow(truth, x, y, t_us):
    wx, wy, wz = truth.angular_velocity(t_us)
    X, Y = (x - truth.cx) / truth.f, (y - truth.cy) / truth.f
    return (truth.f * (X * Y * wx - (1 + X * X) * wy + Y * wz),
            truth.f * ((1 + Y * Y) * wx - X * Y * wy - X * wz))


@pytest.mark.parametrize("kw,times_s", [
    (dict(scenario="high-rise", dynamics="pitch", pitch_amplitude_deg=2.0,
          pitch_first_shift_s=0.1), (0.15, 0.2, 0.33)),
    (dict(scenario="curves", dynamics="curves", start_m=70.0), (0.1, 0.5)),
])
def test_foe_is_the_heading_and_rotation_is_the_cameras(kw, times_s):
    """Under pitch and in curves the true FOE is the projection of the translation (the
    heading): the flow there is the rotational flow of ``angular_velocity`` alone, at whatever
    depth, and not zero; ``angular_velocity`` is the rate of the camera's orientation."""
    sc = Scene.from_params(width=160, height=120, supersample=1, **kw)
    truth = SceneTruth(sc)
    for t in times_s:
        fx, fy = truth.foe(t * 1e6)
        vx, vy = truth.flow(fx, fy, t * 1e6)
        rx, ry = _rotational_flow(truth, fx, fy, t * 1e6)
        assert np.hypot(rx, ry) > 5.0                          # px/s: the camera turns
        assert abs(vx - rx) < 1e-6 * abs(rx) + 1e-9 and abs(vy - ry) < 1e-6 * np.hypot(rx, ry)
        # a point far ahead along the velocity projects onto the FOE
        pos, rot, vc, _ = sc.state(t)
        far = pos + 1e7 * (rot @ vc) / np.linalg.norm(vc)
        np.testing.assert_allclose(sc.project(far[None], t)[0], (fx, fy), atol=1e-3)
        # orientation change over +-dt: R(t)^T R(t + dt) = exp([w]x dt)
        dt = 1e-4
        r0, r1 = sc.state(t - dt)[1], sc.state(t + dt)[1]
        skew = (r0.T @ r1 - r1.T @ r0) / (4 * dt)
        w = np.array(truth.angular_velocity(t * 1e6), float)
        np.testing.assert_allclose([skew[2, 1], skew[0, 2], skew[1, 0]], w, atol=1e-6)
