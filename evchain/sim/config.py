"""Parameters of the driving-scene simulator (scenario, ego motion, camera, lighting).

:class:`SceneConfig` is the base of the ``scene`` source's ``Params``, so a pipeline YAML can vary
every field. Cross-field rules (a route shorter than the drive, dynamics that do not fit the
scenario) raise clear errors; :func:`make_config` turns pydantic's errors into
:class:`~evchain.errors.ConfigError` for Python callers.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from evchain.core.filter import FilterParams
from evchain.errors import ConfigError

Scenario = Literal["high-rise", "high-rise-orange", "open-field", "curves"]

#: Straight-route length in metres of each straight scenario (thesis 4.2).
STRAIGHT_ROUTE_M = {"high-rise": 280.0, "high-rise-orange": 280.0, "open-field": 70.0}

#: The curves route (driving line): (length m, signed curvature 1/m; left > 0).
CURVES_ROUTE = (
    (60.0, 0.0),
    (40.0 * math.pi / 2, 1.0 / 40.0),
    (50.0, 0.0),
    (60.0 * math.radians(75.0), -1.0 / 60.0),
    (60.0, 0.0),
    (80.0 * math.radians(45.0), 1.0 / 80.0),
    (80.0, 0.0),
)


class ImuParams(FilterParams):
    """The simulated camera's IMU (:mod:`evchain.sim.imu`), of the ``scene`` source and of its
    replay ``scene_events``: the same samples for the same parameters and seed."""

    imu_rate_hz: float = Field(0.0, ge=0, le=100_000, description=(
        "samples per second of the camera's simulated IMU (series imu: true gyro and "
        "accelerometer, camera axes); 0: no IMU"))
    imu_gyro_bias_dps: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="gyro bias added to every sample, deg/s (x, y, z)")
    imu_gyro_noise_dps: float = Field(0.0, ge=0, description=(
        "gyro noise, standard deviation per sample, deg/s (seeded)"))
    imu_accel_noise_g: float = Field(0.0, ge=0, description=(
        "accelerometer noise, standard deviation per sample, g (seeded)"))

    def imu_between(self, scene, t_start: int, t_end: int, key: int):
        """The IMU series entries in ``[t_start, t_end)`` with these parameters and the noise
        key ``key`` (:func:`evchain.sim.imu.imu_between`); None without an IMU."""
        from evchain.sim.imu import imu_between

        return imu_between(scene, t_start, t_end, self.imu_rate_hz, key,
                           self.imu_gyro_noise_dps, self.imu_gyro_bias_dps,
                           self.imu_accel_noise_g)


class SceneConfig(FilterParams):
    """Scenario, ego motion and camera of the simulated drive."""

    scenario: Scenario = Field("high-rise", description="scene layout (thesis 4.2, Fig. 4.5)")
    facade: Literal["auto", "grey", "orange"] = Field(
        "auto", description="building texture; auto: orange for high-rise-orange, else grey")
    extra_vertical_lines: bool = Field(
        False, description="vertical lines on the building straight ahead (thesis Fig. 5.1)")
    lanterns: bool = Field(True, description="lantern posts along the road")
    obstacle: bool | None = Field(
        None, description="car across the ego lane at the route end; None: all but curves")
    route_m: float | None = Field(
        None, gt=0, le=5000,
        description="length of the straight route in m (None: 280 high-rise, 70 open field); "
                    "the curves route is fixed (about 452 m)")
    obstacle_gap_m: float = Field(1.0, gt=0, le=100,
                                  description="obstacle rear face beyond the route end, m")
    start_m: float = Field(0.0, ge=0, description="arc length where the drive starts, m")
    duration_s: float | None = Field(
        None, gt=0, description="drive duration in s (None: to the end of the route)")
    speed_mps: float = Field(20.0, ge=0, le=100, description="ego speed in m/s (reference 20)")
    camera_height_m: float = Field(1.2, gt=0, le=50, description="camera height above ground")
    lane_offset_m: float = Field(
        -1.75, ge=-20, le=20, description="driving line relative to the road centre (left > 0)")
    dynamics: Literal["constant", "pitch", "curves", "rotation"] = Field(
        "constant", description="constant: pure translation; pitch: gear-shift pitch "
                                "oscillation (thesis Fig. 4.10); curves: yaw following the road; "
                                "rotation: the camera stands and pans and tilts (pan_dps, "
                                "tilt_dps; speed_mps 0)")
    pan_dps: float = Field(0.0, ge=-360, le=360, description=(
        "dynamics rotation: pan rate, deg/s, to the right > 0 (the renderer cannot roll the "
        "camera, so there is no roll rate)"))
    tilt_dps: float = Field(0.0, ge=-360, le=360,
                            description="dynamics rotation: tilt rate, deg/s, up > 0")
    rotation_start_s: float = Field(0.0, ge=0, description=(
        "dynamics rotation: the camera rests until then (a still start for a gyro bias)"))
    pitch_amplitude_deg: float = Field(1.0, ge=0, le=20, description="pitch oscillation amplitude")
    pitch_frequency_hz: float = Field(2.0, gt=0, le=50, description="pitch oscillation frequency")
    pitch_shift_interval_s: float = Field(3.0, gt=0, description="time between gear shifts")
    pitch_decay_s: float = Field(0.5, gt=0, le=100, description="decay time of each oscillation")
    pitch_first_shift_s: float = Field(0.5, ge=0, description="time of the first gear shift")
    width: int = Field(320, ge=1, le=8192, description="image width in pixels")
    height: int = Field(240, ge=1, le=8192, description="image height in pixels")
    fov_deg: float = Field(35.0, gt=0, lt=180, description="vertical field of view in degrees")
    supersample: int = Field(2, ge=1, le=8, description="k: k x k samples per pixel")
    sun_azimuth_deg: float = Field(40.0, description="sun azimuth from world x towards y")
    sun_elevation_deg: float = Field(35.0, ge=0, le=90, description="sun elevation")
    layout_seed: int = Field(0, ge=0, description="seed of the procedural layout and textures")
    contrast: float = Field(
        1.0, ge=0, le=1, description="log contrast of the frames: intensity I becomes "
        "0.5 (I / 0.5)^contrast, so every log change shrinks by this factor; 0: a uniform grey "
        "frame (no events; the geometry and the ground truth stay those of the scene)")

    @model_validator(mode="after")
    def _check_drive(self):
        if self.scenario == "curves" and self.dynamics != "curves":
            raise ValueError("scenario 'curves' turns: set dynamics: curves (the camera yaws "
                             "with the road)")
        if self.dynamics == "curves" and self.scenario != "curves":
            raise ValueError(f"dynamics 'curves' needs scenario 'curves', got {self.scenario!r}")
        if self.dynamics == "rotation":
            if self.speed_mps != 0:
                raise ValueError("dynamics 'rotation' turns the camera in place: set speed_mps "
                                 f"0 (got {self.speed_mps:g})")
            if self.scenario == "curves":
                raise ValueError("dynamics 'rotation' needs a straight scenario")
            if self.duration_s is not None:
                tilt = abs(self.tilt_dps) * max(self.duration_s - self.rotation_start_s, 0.0)
                if tilt > 80.0:
                    raise ValueError(f"tilt_dps {self.tilt_dps:g} tilts the camera by {tilt:g} "
                                     "deg over the drive; at most 80 (the horizon must stay "
                                     "ahead)")
        elif self.pan_dps or self.tilt_dps or self.rotation_start_s:
            raise ValueError("pan_dps, tilt_dps and rotation_start_s apply to dynamics "
                             f"'rotation', not {self.dynamics!r}")
        if self.scenario == "curves" and self.route_m is not None:
            raise ValueError("route_m applies to straight scenarios; the curves route is fixed")
        route = route_length_m(self)
        if self.start_m > route:
            raise ValueError(f"start_m {self.start_m} m lies beyond the {route:g} m route")
        if self.duration_s is None:
            if self.speed_mps == 0:
                raise ValueError("speed_mps 0 needs an explicit duration_s")
        else:
            end = self.start_m + self.speed_mps * self.duration_s
            if end > route * (1 + 1e-12):
                raise ValueError(
                    f"the route of {route:g} m is shorter than the drive: start_m "
                    f"{self.start_m:g} + speed_mps {self.speed_mps:g} x duration_s "
                    f"{self.duration_s:g} = {end:g} m; shorten the drive or lengthen route_m")
        return self

    @property
    def drive_s(self) -> float:
        """Duration of the drive in seconds."""
        if self.duration_s is not None:
            return float(self.duration_s)
        return (route_length_m(self) - self.start_m) / self.speed_mps

    @property
    def has_obstacle(self) -> bool:
        return self.scenario != "curves" if self.obstacle is None else bool(self.obstacle)

    @property
    def facade_kind(self) -> str:
        if self.facade != "auto":
            return self.facade
        return "orange" if self.scenario == "high-rise-orange" else "grey"


def route_length_m(cfg: SceneConfig) -> float:
    if cfg.scenario == "curves":
        return float(sum(length for length, _ in CURVES_ROUTE))
    return float(cfg.route_m if cfg.route_m is not None else STRAIGHT_ROUTE_M[cfg.scenario])


def make_config(cls: type[SceneConfig] = SceneConfig, **values) -> SceneConfig:
    """Build a config; bad values raise :class:`ConfigError` naming the field and the rule."""
    try:
        return cls(**values)
    except ValidationError as exc:
        msgs = []
        for err in exc.errors():
            key = ".".join(str(p) for p in err["loc"]) or "scene"
            msgs.append(f"{key}: {err['msg']}")
        raise ConfigError("bad scene parameters: " + "; ".join(msgs)) from None
