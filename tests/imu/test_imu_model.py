"""The gyro truth's pieces: rotational flow, gyro track, still bias, checks."""

from __future__ import annotations

import numpy as np
import pytest

from evchain.core.series import IMU
from evchain.imu.calibrate import STILL_US, axis_check, gravity_roll_check, still_bias
from evchain.imu.gyro import GyroTrack
from evchain.imu.rotflow import flow_matrix, rotational_flow


def rotation(w, angle):
    """Rodrigues: rotation by ``angle`` about the unit axis ``w``."""
    w = np.asarray(w, float) / np.linalg.norm(w)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@pytest.mark.parametrize("w", [(0.3, 0, 0), (0, -0.4, 0), (0, 0, 0.7), (0.2, -0.5, 0.9)])
def test_flow_is_the_image_motion_of_a_turning_camera(w):
    """Project scene points before and after the camera turns by w dt: the image moves by the
    flow times dt, whatever the depth."""
    f, cx, cy = 200.0, 110.0, 70.0
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 240, 50)
    y = rng.uniform(0, 180, 50)
    depth = rng.uniform(1, 30, 50)
    p = np.stack([(x - cx) / f * depth, (y - cy) / f * depth, depth])      # camera frame
    dt = 1e-6
    speed = np.linalg.norm(w)
    # the camera turns by +w dt: points turn by -w dt in its frame
    q = rotation(w, -speed * dt) @ p
    u_num = (f * q[0] / q[2] + cx - x) / dt
    v_num = (f * q[1] / q[2] + cy - y) / dt
    u, v = rotational_flow(x, y, np.array(w), f, cx, cy)
    np.testing.assert_allclose(u, u_num, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(v, v_num, rtol=1e-4, atol=1e-3)
    a_u, a_v = flow_matrix(x, y, f, cx, cy)
    np.testing.assert_allclose(a_u @ np.array(w), u, rtol=1e-12)
    np.testing.assert_allclose(a_v @ np.array(w), v, rtol=1e-12)


def test_sign_conventions():
    f, c = 100.0, 50.0
    u, v = rotational_flow(c, c, np.array([0, 1.0, 0]), f, c, c)     # pan right
    assert u < 0 and v == 0                                           # image moves left
    u, v = rotational_flow(c, c, np.array([1.0, 0, 0]), f, c, c)     # tilt up
    assert v > 0 and u == 0                                           # image moves down
    u, v = rotational_flow(c + 10, c, np.array([0, 0, 1.0]), f, c, c)  # roll clockwise
    assert v < 0                     # right of the centre the image moves up: counter-clockwise


def test_gyro_track_interpolation_gaps_bias_and_signs():
    g = GyroTrack()
    t = np.array([0, 1000, 2000, 3000, 20000, 21000], np.int64)
    read = np.stack([t * 1e-3, -t * 1e-3, np.full(len(t), 5.0)], axis=1)
    g.append(t[:3], read[:3])
    g.append(t[3:], read[3:])
    w, ok = g.rate(np.array([500.0, 2999.0, 3000.0, 10_000.0, 20_500.0, 21_001.0, -1.0]),
                   bias_dps=(1.0, 0.0, 5.0), signs=(1, -1, 1))
    np.testing.assert_array_equal(ok, [True, True, True, False, True, False, False])
    np.testing.assert_allclose(np.degrees(w[0]), [0.5 - 1.0, 0.5, 0.0])
    np.testing.assert_allclose(np.degrees(w[4]), [20.5 - 1.0, 20.5, 0.0])
    wp, okp = g.rate(np.array([1999.0, 2000.0]), (0, 0, 0), (1, 1, 1), "previous")
    assert okp.all()
    np.testing.assert_allclose(np.degrees(wp[:, 0]), [1.0, 2.0])
    g.trim(2500)
    assert g.t[0] == 2000 and len(g.until(20_000)) == 2


def imu_entries(t, g, events=None):
    return IMU.array(t=t, ax=0.0, ay=-1.0, az=0.0, gx=g[:, 0], gy=g[:, 1], gz=g[:, 2],
                     temperature_c=30.0)


def test_still_bias_takes_the_quiet_windows():
    rng = np.random.default_rng(0)
    t = np.arange(0, 1_000_000, 1000)
    g = rng.normal(0, 0.1, (len(t), 3)) + [2.0, -1.0, 0.5]
    moving = t >= 400_000
    g[moving, 2] += 30 * np.sin(t[moving] * 1e-5)                    # turning after 0.4 s
    events = {k: (5 if k < 2 else 500) for k in range(5)}
    bias, windows = still_bias(imu_entries(t, g), events)
    assert windows == [(0, STILL_US), (STILL_US, 2 * STILL_US)]
    np.testing.assert_allclose(bias, [2.0, -1.0, 0.5], atol=0.02)
    # a steady gyro while the events are many is a steady turn, not rest
    assert still_bias(imu_entries(t, g), {k: 500 for k in range(5)}) is None
    assert still_bias(imu_entries(t[moving], g[moving]), {}) is None


def test_axis_check():
    gyro = np.array([[0.1, 20.0, -30.0], [0.2, 25.0, -35.0], [0.0, 30.0, -20.0]])
    fit = gyro * [1.0, -1.0, 1.1]
    out = axis_check(gyro, fit)
    assert not out["x"]["checked"] and "0.2 deg/s" in out["x"]["why"]
    assert out["y"]["sign"] == "contradicts" and out["y"]["slope"] == pytest.approx(-1.0)
    assert out["z"]["sign"] == "agrees" and out["z"]["slope"] == pytest.approx(1.1)


def test_gravity_roll_check():
    t = np.arange(0, 2_000_000, 1000)
    wz = 0.5                                        # rad/s, camera rolls clockwise
    up = -np.pi / 2 - wz * t * 1e-6                 # gravity turns the other way
    imu = IMU.array(t=t, ax=np.cos(up), ay=np.sin(up), az=0.0, gx=0.0, gy=0.0,
                    gz=np.degrees(wz) + 0.3, temperature_c=30.0)
    out = gravity_roll_check(imu, 0.3, 1)
    assert out["checked"] and out["ratio"] == pytest.approx(1.0, abs=1e-3)
    assert gravity_roll_check(imu, 0.3, -1)["ratio"] == pytest.approx(-1.0, abs=1e-3)
    tilted = imu.copy()
    tilted["ax"], tilted["ay"], tilted["az"] = 0.1, 0.1, -1.0     # looking at the floor
    assert not gravity_roll_check(tilted, 0.3, 1)["checked"]
