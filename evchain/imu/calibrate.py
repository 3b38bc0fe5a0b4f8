"""Calibrating gyro ground truth against measured normal flow.

The measurement is a local-plane fit of the events' onset times (the ``plane_flow`` filter with
:data:`MEASUREMENT`), used only here: to estimate the principal point and the IMU-event time
offset, to fit the rotation rate the flow shows per time bin, and to decide where the gyro's
flow is the truth (where it agrees with what the events show). A plane fit averages the motion
over the time its neighbours took to be crossed, about ``r / (2 v_n)`` for a neighbourhood of
radius ``r`` px crossed at normal speed ``v_n``: predictions of the *measurement* are taken at
that lag behind the event (:func:`measurement_lag_us`), or the lag would pass for a time offset
(on ``IMU_rotDisk`` about -30 ms instead of +2.5 ms). The truth itself has no lag.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evchain.imu.gyro import GyroTrack
from evchain.imu.rotflow import flow_matrix

#: the measurement: robust plane fits on the surface of each burst's onset (a pixel's events
#: within 150 ms of its previous one neither get flow nor update the surface), with a fixed
#: window, whatever the camera
MEASUREMENT = dict(variant="robust", search_distance=3, window_us=80_000,
                   refractory_us=150_000, refractory_updates=False, max_window_us=0,
                   th2_s=0.004, max_speed_pxs=1000.0)

#: a still stretch: 200 ms windows in which the gyro varies by less than STILL_STD_DPS (standard
#: deviation) and reads less than STILL_MAX_DPS on every axis, with fewer than STILL_EVENT_SHARE
#: of the events of the busiest window
STILL_US = 200_000
STILL_STD_DPS = 0.5
STILL_MAX_DPS = 10.0
STILL_EVENT_SHARE = 0.2

#: an axis sign is checked when the gyro turned at least this fast about the axis (deg/s)
AXIS_CHECK_DPS = 5.0
#: the gravity check of the roll needs the gravity in the image plane (g) and a turn (deg)
GRAVITY_MIN_G = 0.5
GRAVITY_MIN_TURN_DEG = 10.0

#: the cost of a time offset within this factor of the best one counts as equally good
OFFSET_TIE = 1.02


@dataclass
class Measured:
    """Measured normal flow: pixel ``x, y``, time ``t`` (µs) and ``vx, vy`` (px/s)."""

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    vx: np.ndarray
    vy: np.ndarray

    @classmethod
    def empty(cls) -> Measured:
        z = np.zeros(0)
        return cls(z, z, z, z, z)

    @classmethod
    def concat(cls, parts: list[Measured]) -> Measured:
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, k) for p in parts])
                     for k in ("x", "y", "t", "vx", "vy")))

    def select(self, mask) -> Measured:
        return Measured(self.x[mask], self.y[mask], self.t[mask], self.vx[mask], self.vy[mask])

    def __len__(self) -> int:
        return len(self.t)

    @property
    def speed(self) -> np.ndarray:
        return np.hypot(self.vx, self.vy)

    def normal(self) -> tuple[np.ndarray, np.ndarray]:
        s = np.maximum(self.speed, 1e-12)
        return self.vx / s, self.vy / s


@dataclass(frozen=True)
class Camera:
    """What turns gyro readings into flow: focal length and principal point (px), gyro bias
    (deg/s, camera axes, subtracted before the signs apply), axis signs, IMU-event time offset
    (µs: the sample stamped ``t + offset`` describes the motion at event time ``t``) and the
    interpolation between samples."""

    f: float
    cx: float
    cy: float
    bias_dps: tuple[float, float, float]
    signs: tuple[int, int, int]
    offset_us: float
    interpolation: str = "linear"

    def replace(self, **changes) -> Camera:
        return Camera(**{**self.__dict__, **changes})


def measurement_lag_us(p_normal: np.ndarray) -> np.ndarray:
    """How far (µs) the measurement lags the motion at predicted normal speed ``p_normal``."""
    r = MEASUREMENT["search_distance"]
    cap = MEASUREMENT["window_us"] / 2.0
    return np.minimum(r / (2.0 * np.maximum(np.abs(p_normal), 1e-3)) * 1e6, cap)


def predict_normal(meas: Measured, gyro: GyroTrack, cam: Camera, lag: bool = True
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(p, covered)``: the gyro's flow along each measured normal (px/s), at the lag the
    measurement has (``lag``) or at the event time."""
    nx, ny = meas.normal()
    a_u, a_v = flow_matrix(meas.x, meas.y, cam.f, cam.cx, cam.cy)
    rows = nx[:, None] * a_u + ny[:, None] * a_v
    w, covered = gyro.rate(meas.t + cam.offset_us, cam.bias_dps, cam.signs, cam.interpolation)
    p = np.einsum("ij,ij->i", rows, w)
    if lag:
        w, covered = gyro.rate(meas.t + cam.offset_us - measurement_lag_us(p), cam.bias_dps,
                               cam.signs, cam.interpolation)
        p = np.einsum("ij,ij->i", rows, w)
    return p, covered


def relative_normal_error(meas: Measured, p: np.ndarray) -> np.ndarray:
    """``|measured normal speed - p| / |p|`` per measurement."""
    return np.abs(meas.speed - p) / np.maximum(np.abs(p), 1e-12)


# ---------------------------------------------------------------------------------------------
# bias


def still_bias(imu: np.ndarray, window_events: dict[int, int]
               ) -> tuple[tuple[float, float, float], list[tuple[int, int]]] | None:
    """The gyro bias (deg/s) as the mean reading over the still windows of ``imu`` (IMU
    series entries), and those windows ``[(t0, t1)]``; None if there is none. ``window_events``
    counts the events per window index ``t // STILL_US``."""
    if len(imu) == 0:
        return None
    k = imu["t"] // STILL_US
    g = np.stack([imu["gx"], imu["gy"], imu["gz"]], axis=1)
    busiest = max(window_events.values(), default=0)
    chosen = []
    for kk in np.unique(k):
        m = k == kk
        if np.count_nonzero(m) < 10:
            continue
        gm = g[m]
        if (np.all(gm.std(axis=0) < STILL_STD_DPS) and np.all(np.abs(gm.mean(axis=0))
                                                              < STILL_MAX_DPS)
                and window_events.get(int(kk), 0) <= STILL_EVENT_SHARE * busiest):
            chosen.append(int(kk))
    if not chosen:
        return None
    m = np.isin(k, chosen)
    bias = g[m].mean(axis=0)
    return (float(bias[0]), float(bias[1]), float(bias[2])), [(c * STILL_US, (c + 1) * STILL_US)
                                                              for c in chosen]


# ---------------------------------------------------------------------------------------------
# principal point and time offset


@dataclass
class CameraFit:
    """The result of :func:`fit_camera`."""

    camera: Camera
    cost: float                      # median |measured - predicted| normal speed, px/s
    n: int                           # measurements used
    offsets_us: np.ndarray           # offsets tried
    costs: np.ndarray                # their cost
    offset_range_us: tuple[float, float]   # offsets within OFFSET_TIE of the best


def _principal_point(meas: Measured, rows_w: tuple[np.ndarray, ...], cam: Camera,
                     iterations: int = 6) -> tuple[float, float, float]:
    """Robust Gauss-Newton for ``(cx, cy)`` with the rates at the measurements fixed;
    returns ``(cx, cy, median |residual|)``."""
    nx, ny, w, s = rows_w
    cx, cy = cam.cx, cam.cy

    def resid(cx_, cy_):
        a_u, a_v = flow_matrix(meas.x, meas.y, cam.f, cx_, cy_)
        return s - np.einsum("ij,ij->i", nx[:, None] * a_u + ny[:, None] * a_v, w)

    step = 0.5
    for _ in range(iterations):
        r = resid(cx, cy)
        jac = np.stack([(resid(cx + step, cy) - r) / step, (resid(cx, cy + step) - r) / step],
                       axis=1)
        scale = 1.4826 * float(np.median(np.abs(r))) + 1e-9
        wt = 1.0 / (1.0 + (r / (2.0 * scale)) ** 2)        # Cauchy weights
        h = (jac * wt[:, None]).T @ jac
        if np.linalg.cond(h) > 1e12:
            break
        d = -np.linalg.solve(h, (jac * wt[:, None]).T @ r)
        cx, cy = cx + float(d[0]), cy + float(d[1])
        if np.hypot(*d) < 1e-3:
            break
    return cx, cy, float(np.median(np.abs(resid(cx, cy))))


def fit_camera(meas: Measured, gyro: GyroTrack, cam: Camera, fit_centre: bool,
               fit_offset: bool, max_offset_us: int, min_speed_pxs: float) -> CameraFit | None:
    """Estimate the principal point (``fit_centre``) and the time offset (``fit_offset``,
    within ``±max_offset_us``) that make the gyro's flow agree best with ``meas`` (median
    absolute normal-speed residual, the measurement's lag modelled); ``cam`` gives the start
    and the fixed parts. None without enough measurements where the gyro's flow is at least
    ``min_speed_pxs``."""
    p, covered = predict_normal(meas, gyro, cam, lag=False)
    use = covered & (np.abs(p) >= min_speed_pxs)
    if np.count_nonzero(use) < 20:
        return None
    meas = meas.select(use)
    nx, ny = meas.normal()
    s = meas.speed
    if fit_offset:
        step = max(500.0, float(np.ceil(2 * max_offset_us / 40 / 500) * 500))
        grid = np.arange(-max_offset_us, max_offset_us + 0.5 * step, step)
    else:
        grid = np.array([cam.offset_us])
    best = cam
    costs = np.empty(len(grid))

    def at_offset(offset: float, start: Camera) -> tuple[Camera, float]:
        trial = start.replace(offset_us=float(offset))
        p0, _ = predict_normal(meas, gyro, trial, lag=False)
        w, _ = gyro.rate(meas.t + offset - measurement_lag_us(p0), trial.bias_dps, trial.signs,
                         trial.interpolation)
        if fit_centre:
            cx, cy, cost = _principal_point(meas, (nx, ny, w, s), trial)
            return trial.replace(cx=cx, cy=cy), cost
        p, _ = predict_normal(meas, gyro, trial)
        return trial, float(np.median(np.abs(s - p)))

    fits = []
    for i, off in enumerate(grid):
        c, costs[i] = at_offset(off, best if fits else cam)
        fits.append(c)
        if costs[i] <= costs[:i + 1].min():
            best = c
    i = int(np.argmin(costs))
    chosen, cost = fits[i], float(costs[i])
    if fit_offset and 0 < i < len(grid) - 1:       # parabola through the best three
        c0, c1, c2 = costs[i - 1:i + 2]
        denom = c0 - 2 * c1 + c2
        if denom > 0:
            off = grid[i] + 0.5 * (c0 - c2) / denom * (grid[1] - grid[0])
            c, cst = at_offset(off, chosen)
            if cst <= cost:
                chosen, cost = c, cst
    tied = grid[costs <= OFFSET_TIE * costs.min()]
    return CameraFit(chosen, cost, len(meas), grid, costs, (float(tied.min()), float(tied.max())))


# ---------------------------------------------------------------------------------------------
# rates per bin and checks


def fit_rate(meas: Measured, f: float, cx: float, cy: float, iterations: int = 6
             ) -> np.ndarray | None:
    """The angular velocity (rad/s, camera axes) whose flow best explains the measured normal
    speeds (robust least squares); None with fewer than 10 measurements or a degenerate set."""
    if len(meas) < 10:
        return None
    nx, ny = meas.normal()
    a_u, a_v = flow_matrix(meas.x, meas.y, f, cx, cy)
    rows = nx[:, None] * a_u + ny[:, None] * a_v
    s = meas.speed
    wt = np.ones(len(s))
    w = None
    for _ in range(iterations):
        h = (rows * wt[:, None]).T @ rows
        if np.linalg.cond(h) > 1e10:
            return None
        w = np.linalg.solve(h, (rows * wt[:, None]).T @ s)
        r = s - rows @ w
        scale = 1.4826 * float(np.median(np.abs(r))) + 1e-9
        wt = 1.0 / (1.0 + (r / (2.0 * scale)) ** 2)
    return w


def axis_check(gyro_dps: np.ndarray, fit_dps: np.ndarray) -> dict[str, object]:
    """Per camera axis: does the rate fitted to the flow turn the way the gyro says? ``gyro_dps``
    and ``fit_dps`` are ``[bins, 3]`` (NaN rows skipped). An axis is checked when the gyro
    turned at least :data:`AXIS_CHECK_DPS` about it; the slope of fit against gyro (through 0)
    is then positive when the signs agree."""
    ok = np.all(np.isfinite(gyro_dps), axis=1) & np.all(np.isfinite(fit_dps), axis=1)
    out: dict[str, object] = {}
    for k, axis in enumerate("xyz"):
        g = gyro_dps[ok, k]
        fit = fit_dps[ok, k]
        peak = float(np.max(np.abs(g))) if len(g) else 0.0
        if peak < AXIS_CHECK_DPS:
            out[axis] = {"checked": False,
                         "why": f"the gyro turned at most {peak:.1f} deg/s about {axis} "
                                f"(a check needs {AXIS_CHECK_DPS:g})"}
            continue
        slope = float(np.dot(fit, g) / np.dot(g, g))
        out[axis] = {"checked": True, "slope": slope, "sign": "agrees" if slope > 0
                     else "contradicts", "peak_gyro_dps": peak}
    return out


def gravity_roll_check(imu: np.ndarray, bias_z_dps: float, sign_z: int) -> dict[str, object]:
    """The roll the gyro integrates against the turn of gravity in the image plane (from the
    accelerometer). With the camera's axes as in :mod:`evchain.io.davis_imu`, gravity's
    direction in the x-y plane turns at ``-wz``: the ratio of the two turns is near 1 when the
    gyro's roll axis, sign and scale are right."""
    if len(imu) < 2:
        return {"checked": False, "why": "fewer than 2 IMU samples"}
    axy = np.hypot(imu["ax"], imu["ay"])
    if np.min(axy) < GRAVITY_MIN_G:
        return {"checked": False, "why": f"gravity is not in the image plane (at least "
                                         f"{GRAVITY_MIN_G:g} g needed, {np.min(axy):.2f} g seen)"}
    psi = np.degrees(np.unwrap(np.arctan2(imu["ay"], imu["ax"])))
    t_s = (imu["t"] - imu["t"][0]) * 1e-6
    wz = sign_z * (imu["gz"] - bias_z_dps)
    gyro_turn = -float(np.sum(0.5 * (wz[1:] + wz[:-1]) * np.diff(t_s)))
    grav_turn = float(psi[-1] - psi[0])
    if abs(gyro_turn) < GRAVITY_MIN_TURN_DEG:
        return {"checked": False, "why": f"the camera rolled only {gyro_turn:.1f} deg"}
    return {"checked": True, "span_s": float(t_s[-1]), "gravity_turn_deg": grav_turn,
            "gyro_turn_deg": gyro_turn, "ratio": grav_turn / gyro_turn}
