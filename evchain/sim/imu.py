"""The simulated camera's inertial unit: the true gyro and accelerometer of a scene's camera.

In the camera's axes (x right, y down, z forward) and the units of the series
:data:`~evchain.core.series.IMU`, as the ``aedat`` source reads a DAVIS camera's: the gyro is
the camera's angular velocity (deg/s), the accelerometer its specific force (g: acceleration
minus gravity, so an upright camera at rest reads ay = -1), from the trajectory the renderer
uses. The acceleration is a central difference of the velocity over ±ACCEL_STEP_US.

The noise of a sample is a function of a key (from the run's seed and the stage) and the
sample's time only (:func:`sample_normals`), so it does not depend on how the stream is cut
into packets: a replay (``scene_events``, other packets) draws the recording's noise.
"""

from __future__ import annotations

import numpy as np

from evchain.core.series import IMU

#: standard gravity, m/s^2
GRAVITY = 9.80665
#: step of the velocity's central difference, µs
ACCEL_STEP_US = 100.0


def _states(scene, t_us: np.ndarray):
    from evchain.kernels.scene_geometry import camera_states

    t = np.ascontiguousarray(np.asarray(t_us, np.float64).ravel()) * 1e-6
    n = len(t)
    pos, rot, vc, wc = np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 3))
    if n:
        camera_states(t, scene.segs, scene.traj, pos, rot, vc, wc)
    return rot, vc, wc


def true_imu(scene, t_us) -> tuple[np.ndarray, np.ndarray]:
    """``(gyro deg/s [n, 3], accelerometer g [n, 3])`` of ``scene``'s camera at ``t_us``."""
    t = np.asarray(t_us, np.float64).ravel()
    rot, _, wc = _states(scene, t)
    r0, v0, _ = _states(scene, t - ACCEL_STEP_US)
    r1, v1, _ = _states(scene, t + ACCEL_STEP_US)
    vw0 = np.einsum("nij,nj->ni", r0, v0)
    vw1 = np.einsum("nij,nj->ni", r1, v1)
    acc = (vw1 - vw0) / (2 * ACCEL_STEP_US * 1e-6)
    acc[:, 2] += GRAVITY                              # specific force: minus gravity (-z)
    return np.degrees(wc), np.einsum("nji,nj->ni", rot, acc) / GRAVITY


#: splitmix64's increment and multipliers (Steele, Lea and Flood 2014)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1, _MIX2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)


def noise_key(context, stage_id: str) -> int:
    """The 63-bit key for :func:`sample_normals` of the stage ``stage_id``: drawn from the
    run's seeded stream ``STAGE_ID.imu`` (``context.rng``), so the ``scene`` source, a replay
    under the same id and the bench inputs all get the same noise."""
    return int(context.rng(f"{stage_id}.imu").integers(0, 2**63))


def sample_normals(key: int, t_us, n: int) -> np.ndarray:
    """``[len(t_us), n]`` standard normal values that depend only on ``key``, the sample's time,
    the column and ``n``: counter-based, each the splitmix64 hash of the key and the counter
    ``t * n' + column`` (n' = n rounded up to even), made normal by Box-Muller."""
    m = n + n % 2
    t = np.asarray(t_us, np.int64).ravel().astype(np.uint64)[:, None]
    z = (t * np.uint64(m) + np.arange(1, m + 1, dtype=np.uint64)[None, :]) * _GOLDEN
    z += np.uint64(key)                                    # uint64 arrays wrap, as intended
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    z ^= z >> np.uint64(31)
    u = (z >> np.uint64(11)).astype(np.float64) * 2.0**-53          # [0, 1), 53 bits
    r = np.sqrt(-2.0 * np.log1p(-u[:, 0::2]))                       # 1 - u in (0, 1]
    phi = 2.0 * np.pi * u[:, 1::2]
    return np.concatenate([r * np.cos(phi), r * np.sin(phi)], axis=1)[:, :n]


def imu_samples(scene, t_us, key: int = 0, gyro_noise_dps: float = 0.0,
                gyro_bias_dps=(0.0, 0.0, 0.0), accel_noise_g: float = 0.0,
                temperature_c: float = 25.0) -> np.ndarray:
    """IMU series entries at ``t_us``: the true readings plus ``gyro_bias_dps`` and Gaussian
    noise (standard deviations per sample; :func:`sample_normals` of ``key``, so each
    sample's noise depends only on the key and its time)."""
    t = np.asarray(t_us, np.int64).ravel()
    gyro, accel = true_imu(scene, t)
    gyro = gyro + np.asarray(gyro_bias_dps, np.float64)
    if gyro_noise_dps or accel_noise_g:
        z = sample_normals(key, t, 6)
        gyro = gyro + gyro_noise_dps * z[:, :3]
        accel = accel + accel_noise_g * z[:, 3:]
    return IMU.array(t=t, ax=accel[:, 0], ay=accel[:, 1], az=accel[:, 2], gx=gyro[:, 0],
                     gy=gyro[:, 1], gz=gyro[:, 2], temperature_c=np.full(len(t), temperature_c))


def imu_between(scene, t_start: int, t_end: int, rate_hz: float, key: int,
                gyro_noise_dps: float = 0.0, gyro_bias_dps=(0.0, 0.0, 0.0),
                accel_noise_g: float = 0.0) -> np.ndarray | None:
    """The IMU series entries of :func:`imu_samples` in ``[t_start, t_end)`` on the grid
    ``k / rate_hz`` (µs, rounded); None when ``rate_hz`` is 0 (no IMU)."""
    if rate_hz <= 0:
        return None
    step = 1e6 / rate_hz
    k = np.arange(np.ceil(t_start / step), np.ceil(t_end / step))
    t = np.unique(np.rint(k * step).astype(np.int64))
    t = t[(t >= t_start) & (t < t_end)]
    return imu_samples(scene, t, key, gyro_noise_dps, gyro_bias_dps, accel_noise_g)
