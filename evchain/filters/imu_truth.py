"""Stage ``imu_truth``: ground-truth flow for real recordings from the camera's gyro.

When the camera only rotates, the optical flow follows from its angular velocity alone
(Rueckauer & Delbruck 2016, the DVSFLOW16 paper). This stage reads the IMU series the source
delivers, calibrates the camera model against normal flow it measures itself, and sets the
gyro's flow as ``context.truth`` for the stages after it, valid only where the events show a
pure rotation (see ``docs/explanation/imu_truth.md``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Context, Filter, FilterParams
from evchain.core.packets import EventPacket
from evchain.core.series import IMU, IMU_RATE
from evchain.core.truth import FlowTruth, FoeTruth, RotationTruth, TtcTruth
from evchain.errors import DataError

#: DAVIS240C (18.5 µm pixels) behind the 4.5 mm lens of the DVSFLOW16 recordings, px
DAVIS240C_FOCAL_PX = 4.5 / 0.0185
#: gyro samples after a bin's end (beyond the largest offset) that its decision waits for, µs
IMU_MARGIN_US = 20_000


class ImuTruth(Filter):
    """Ground truth from the gyro: the rotational flow, where the events confirm a rotation.

    For each event time t the angular velocity is the gyro's at ``t + time_offset_us`` (bias
    removed, ``axis_signs`` applied, interpolated); the flow follows from it, ``focal_px`` and
    the principal point. Calibration, on the first ``calibration_us`` of the input (held back
    until then): the gyro bias from a still stretch unless given, then the principal point and
    the IMU-event time offset (each unless given) that make the gyro's flow agree best with
    normal flow measured here by robust local plane fits. After it, per ``bin_us`` bin, the
    measured normal flow is compared with the gyro's: the truth holds in bins where their
    median relative difference is at most ``max_normal_error`` (with at least
    ``min_measurements`` measurements), and where the true flow is at least ``min_speed_pxs``;
    elsewhere it is NaN (camera translation, moving objects, too slow, no gyro). Sets
    ``context.truth`` for later stages, replacing the source's: the flow, the camera's
    angular velocity (the gyro's, wherever it has samples) and, since the gyro tells no
    heading, a FOE and TTC that are NaN throughout (:class:`~evchain.imu.truth.ImuFlowTruth`).
    Passes the events on, late by up to a bin plus ``max_offset_us`` (and by the calibration
    lead-in at the start), with the series ``imu_rate`` (gyro rate against the rate fitted to
    the measured flow per bin). ``metrics.imu_truth`` reports the camera model used, the
    estimates, the checks of the axis signs and of the roll against gravity, and the share of
    events with truth.
    """

    name = "imu_truth"
    consumes = EventPacket
    produces = EventPacket
    needs_series = (IMU,)
    adds_series = (IMU_RATE,)
    provides_truth = (FlowTruth, FoeTruth, RotationTruth, TtcTruth)

    class Params(FilterParams):
        focal_px: float | None = Field(
            None, gt=0, description="focal length, px; default: the sensor geometry's when the "
            "source knows it, else 243.2 (DAVIS240C: 18.5 µm pixels, 4.5 mm lens)")
        principal_point_px: tuple[float, float] | None = Field(
            None, description="principal point (x, y) in px, top-left origin; default: "
            "estimated from the flow, starting at the sensor centre")
        axis_signs: tuple[Literal[-1, 1], Literal[-1, 1], Literal[-1, 1]] = Field(
            (1, 1, 1), description="signs applied to the gyro's x, y, z rates (after the "
            "bias) to get the camera's; checked against the flow and reported")
        gyro_bias_dps: tuple[float, float, float] | None = Field(
            None, description="gyro reading at rest (x, y, z deg/s, camera axes), subtracted; "
            "default: the mean over the still stretches of the calibration lead-in")
        time_offset_us: int | None = Field(
            None, description="the gyro sample stamped t + offset describes event time t; "
            "default: estimated within max_offset_us")
        max_offset_us: int = Field(50_000, ge=0, le=1_000_000,
                                   description="largest time offset searched, µs")
        interpolation: Literal["linear", "previous"] = Field(
            "linear", description="gyro between samples: linear, or the latest sample (jAER)")
        calibration_us: int = Field(2_000_000, ge=10_000, le=600_000_000, description=(
            "lead-in used to calibrate, µs; the output starts after it"))
        bin_us: int = Field(100_000, ge=1_000, le=10_000_000,
                            description="time bin of the validity check and of imu_rate, µs")
        max_normal_error: float = Field(0.5, gt=0, description=(
            "a bin's truth holds when the median relative difference between measured and "
            "gyro normal speed is at most this"))
        min_measurements: int = Field(50, ge=1, description=(
            "fewest measured normal flows for a bin's check (fewer: no truth there)"))
        min_speed_pxs: float = Field(10.0, ge=0, description=(
            "no truth where the gyro's flow is slower than this, px/s"))

    def setup(self, params, context) -> None:
        from evchain.imu.truth import ImuFlowTruth

        self.provider = ImuFlowTruth(params.bin_us, params.min_speed_pxs)
        super().setup(params, context)
        context.truth = self.provider

    def reset(self) -> None:
        from evchain.filters.plane_flow import PlaneFlow
        from evchain.imu.calibrate import MEASUREMENT

        self.provider.clear()
        self._measure = PlaneFlow()
        self._measure.id = f"{self.id}.measurement"
        self._measure.setup(PlaneFlow.Params(**MEASUREMENT),
                            Context(geometry=self.context.geometry))
        self._held: list[EventPacket] = []
        self._meas: list = []
        self._lead_imu: list[np.ndarray] = []
        self._window_events: dict[int, int] = {}
        self._t_first: int | None = None
        self._input_end = 0
        self._released = 0
        self._geometry = self.context.geometry
        self._calibrated = False
        self._report: dict = {}
        self._next_bin = 0
        self._decided_until = -(1 << 62)
        self._rates: list[tuple] = []       # imu_rate rows not yet sent
        self._all_rates: list[tuple] = []
        self._bins = {"valid": 0, "disagree": 0, "few_measurements": 0, "no_gyro": 0}
        self._n_in = 0
        self._n_truth = 0
        self._imu_seen = 0

    # -- streaming ------------------------------------------------------------------------------

    def process(self, packet: EventPacket) -> EventPacket:
        from evchain.imu.calibrate import MEASUREMENT, STILL_US, Measured

        prm = self.params
        if self._t_first is None:
            self._t_first = self._released = packet.t_start
        # the events sent so far have been scored: gyro samples before the earliest time a
        # later event or measurement can ask for (lagged by up to the measurement's window)
        # are no longer needed
        self.provider.gyro.trim(self._released - prm.max_offset_us - IMU_MARGIN_US
                                - MEASUREMENT["window_us"])
        self._input_end = packet.t_end
        self._geometry = packet.geometry
        imu = packet.series.get(IMU.name, np.zeros(0, IMU.dtype))
        self._imu_seen += len(imu)
        self.provider.gyro.append(imu["t"], np.stack([imu["gx"], imu["gy"], imu["gz"]], axis=1))
        if not self._calibrated:
            self._lead_imu.append(imu)
            k, n = np.unique(packet.t // STILL_US, return_counts=True)
            for kk, nn in zip(k.tolist(), n.tolist(), strict=True):
                self._window_events[kk] = self._window_events.get(kk, 0) + nn
        flow = self._measure.process(packet)
        if len(flow):
            self._meas.append(Measured(flow.x.astype(np.float64), flow.y.astype(np.float64),
                                       flow.t.astype(np.float64), flow.vx.astype(np.float64),
                                       flow.vy.astype(np.float64)))
        self._held.append(packet)
        wait = prm.max_offset_us + IMU_MARGIN_US
        if not self._calibrated and self._input_end >= self._lead_end() + wait:
            self._calibrate(final=False)
        if self._calibrated:
            self._decide_bins((self._input_end - wait) // prm.bin_us)
        return self._release(final=False)

    def flush(self) -> EventPacket | None:
        if self._t_first is None:
            return None
        if not self._calibrated:
            self._calibrate(final=True)
        self._decide_bins((self._input_end - 1) // self.params.bin_us + 1)
        out = self._release(final=True)
        self._write_metrics()
        return out

    def _lead_end(self) -> int:
        return self._t_first + self.params.calibration_us

    def _release(self, final: bool) -> EventPacket:
        """The held packets whose bins are decided (all of them at the end), as one packet
        with the imu_rate entries of its slice; an empty packet at the release point if none."""
        if final:
            ready, self._held = self._held, []
        else:
            n = 0
            while n < len(self._held) and self._held[n].t_end <= self._decided_until:
                n += 1
            ready, self._held = self._held[:n], self._held[n:]
        if ready:
            out = ready[0] if len(ready) == 1 else EventPacket.concat(ready)
        else:
            out = EventPacket.empty(self._geometry, self._released, self._released)
        if len(out):
            self._n_in += len(out)
            self._n_truth += int(np.count_nonzero(self.provider.valid(out.x, out.y, out.t)))
        rows = self._rates
        if final:
            last = max(out.t_end - 1, out.t_start)
            mine = [(min(max(r[0], out.t_start), last), *r[1:]) for r in rows]
            self._rates = []
        else:
            mine = [r for r in rows if r[0] < out.t_end]
            self._rates = [r for r in rows if r[0] >= out.t_end]
        self._released = out.t_end
        return out.with_series(IMU_RATE.name, np.array(mine, IMU_RATE.dtype))

    # -- calibration ----------------------------------------------------------------------------

    def _camera_start(self, bias):
        from evchain.imu.calibrate import Camera

        prm = self.params
        g = self._geometry
        f = prm.focal_px or (g.f if g is not None and g.f else DAVIS240C_FOCAL_PX)
        cx, cy = prm.principal_point_px or (g.cx, g.cy)
        return Camera(float(f), float(cx), float(cy), bias, tuple(prm.axis_signs),
                      float(prm.time_offset_us or 0), prm.interpolation)

    def _calibrate(self, final: bool) -> None:
        from evchain.imu.calibrate import (
            Measured,
            fit_camera,
            gravity_roll_check,
            predict_normal,
            relative_normal_error,
            still_bias,
        )

        prm = self.params
        lead_end = self._lead_end()
        imu = np.concatenate(self._lead_imu) if self._lead_imu else np.zeros(0, IMU.dtype)
        imu = imu[imu["t"] < lead_end]
        self._lead_imu = []
        gyro = self.provider.gyro if final else self.provider.gyro.until(
            lead_end + prm.max_offset_us + IMU_MARGIN_US)
        if len(gyro) == 0:
            raise DataError(
                f"{self.id}: the input carries no IMU samples (series 'imu') up to "
                f"{(lead_end if not final else self._input_end) * 1e-6:.3f} s: gyro ground "
                "truth needs the camera's gyro; the source's file has no IMU records (see the "
                "source's metrics imu_samples) or the source does not read them")
        if prm.gyro_bias_dps is not None:
            bias, bias_from = tuple(map(float, prm.gyro_bias_dps)), "given"
        else:
            found = still_bias(imu, self._window_events)
            if found is None:
                raise DataError(
                    f"{self.id}: no still stretch in the first "
                    f"{prm.calibration_us * 1e-6:g} s to take the gyro bias from (200 ms in "
                    "which the gyro is steady within 0.5 deg/s and below 10 deg/s, with few "
                    "events): give gyro_bias_dps (the gyro's reading at rest, camera axes), or "
                    "start the recording with the camera still")
            bias, windows = found
            bias_from = (f"still stretch: {len(windows)} x 200 ms from "
                         f"{windows[0][0] * 1e-6:.3f} s")
        start = self._camera_start(bias)
        meas = Measured.concat(self._meas)
        lead = meas.select(meas.t < lead_end)
        fit = fit_camera(lead, gyro, start, prm.principal_point_px is None,
                         prm.time_offset_us is None, prm.max_offset_us, prm.min_speed_pxs)
        cam = start if fit is None else fit.camera
        p, covered = predict_normal(lead, gyro, cam)
        use = covered & (np.abs(p) >= prm.min_speed_pxs)
        err = (float(np.median(relative_normal_error(lead.select(use), p[use])))
               if use.any() else None)
        estimated = prm.principal_point_px is None or prm.time_offset_us is None
        accepted = fit is not None and err is not None and err <= prm.max_normal_error
        if estimated and not accepted:
            why = (f"only {int(np.count_nonzero(use))} measured normal flows where the gyro's "
                   "flow is fast enough" if fit is None or err is None else
                   f"the measured normal flow differs from the gyro's by {100 * err:.0f} % "
                   f"(median) at best, more than max_normal_error {prm.max_normal_error:g}")
            self.context.warn(
                f"{self.id}: principal point and time offset not estimated ({why}; camera "
                "translation, moving objects, or wrong axis_signs/focal_px?); using "
                f"({start.cx:.1f}, {start.cy:.1f}) px and {start.offset_us:g} us")
            cam = start
        halves = None
        if accepted and prm.principal_point_px is None:
            # the estimate's spread: the same fit on each half of the calibration stretch
            mid = float(np.median(lead.t))
            halves = []
            for part in (lead.select(lead.t < mid), lead.select(lead.t >= mid)):
                h = fit_camera(part, gyro, cam, True, False, 0, prm.min_speed_pxs)
                halves.append(None if h is None else [h.camera.cx, h.camera.cy])
        self.provider.camera = cam
        self._calibrated = True
        self._next_bin = self._t_first // prm.bin_us
        g = self._geometry
        self._report = {
            "lead_in_s": (min(lead_end, self._input_end) - self._t_first) * 1e-6,
            "measurements": len(lead),
            "median_normal_error": err,
            "estimate": None if fit is None else {
                "principal_point_px": [fit.camera.cx, fit.camera.cy],
                "time_offset_us": fit.camera.offset_us,
                "time_offset_range_us": list(fit.offset_range_us),
                "median_residual_pxs": fit.cost, "measurements_used": fit.n,
                "accepted": accepted,
                "principal_point_halves_px": halves},
            "bias_from": bias_from,
            "principal_point_from": ("given" if prm.principal_point_px is not None else
                                     "estimated" if accepted else "sensor centre"),
            "time_offset_from": ("given" if prm.time_offset_us is not None else
                                 "estimated" if accepted else "0"),
            "gravity_roll": gravity_roll_check(imu, bias[2], prm.axis_signs[2]),
            "sensor_centre_px": None if g is None else [g.cx, g.cy],
        }

    # -- validity per bin -----------------------------------------------------------------------

    def _decide_bins(self, upto: int) -> None:
        """Decide bins ``next_bin .. upto - 1``."""
        from evchain.imu.calibrate import Measured

        if self._next_bin >= upto:
            return
        B = self.params.bin_us
        meas = Measured.concat(self._meas)
        k = np.floor_divide(meas.t, B).astype(np.int64)
        for kk in range(self._next_bin, upto):
            self._decide(kk, meas.select(k == kk))
        rest = k >= upto
        self._meas = [meas.select(rest)] if rest.any() else []
        self._next_bin = upto
        self._decided_until = upto * B

    def _decide(self, k: int, meas) -> None:
        from evchain.imu.calibrate import (
            fit_rate,
            measurement_lag_us,
            predict_normal,
            relative_normal_error,
        )

        prm = self.params
        cam = self.provider.camera
        p, covered = predict_normal(meas, self.provider.gyro, cam)
        use = covered & (np.abs(p) >= prm.min_speed_pxs)
        n = int(np.count_nonzero(use))
        err = float(np.median(relative_normal_error(meas.select(use), p[use]))) if n else np.nan
        centre = (k + 0.5) * prm.bin_us + cam.offset_us
        if covered.any():     # at the times the measurement reflects (see measurement_lag_us)
            w, _ = self.provider.gyro.rate(
                meas.t[covered] + cam.offset_us - measurement_lag_us(p[covered]), cam.bias_dps,
                cam.signs, cam.interpolation)
            gyro = np.degrees(w.mean(axis=0))
        else:
            w, cov = self.provider.gyro.rate(np.array([centre]), cam.bias_dps, cam.signs,
                                             cam.interpolation)
            gyro = np.degrees(w[0]) if cov[0] else np.full(3, np.nan)
        fitted = fit_rate(meas.select(covered), cam.f, cam.cx, cam.cy)
        fitted = np.full(3, np.nan) if fitted is None else np.degrees(fitted)
        if not np.all(np.isfinite(gyro)):
            reason = "no_gyro"
        elif n < prm.min_measurements:
            reason = "few_measurements"
        elif err > prm.max_normal_error:
            reason = "disagree"
        else:
            reason = "valid"
        if len(meas) == 0 and reason == "few_measurements" and not self._bin_has_input(k):
            return      # no events at all in this bin: nothing to decide or to report
        self._bins[reason] += 1
        valid = reason == "valid"
        self.provider.set_bin(k, valid)
        row = ((k + 1) * prm.bin_us - 1, n, *gyro, *fitted, err, int(valid))
        self._rates.append(row)
        self._all_rates.append(row)

    def _bin_has_input(self, k: int) -> bool:
        B = self.params.bin_us
        return any(len(p) and p.t[0] < (k + 1) * B and p.t[-1] >= k * B for p in self._held)

    # -- report ---------------------------------------------------------------------------------

    def _write_metrics(self) -> None:
        from evchain.imu.calibrate import axis_check

        prm = self.params
        cam = self.provider.camera
        rates = np.array(self._all_rates, IMU_RATE.dtype)
        valid = rates["valid"] == 1
        gyro = np.stack([rates["gx"], rates["gy"], rates["gz"]], axis=1)[valid]
        fitted = np.stack([rates["fit_gx"], rates["fit_gy"], rates["fit_gz"]], axis=1)[valid]
        axes = axis_check(gyro, fitted)
        share = self._n_truth / self._n_in if self._n_in else None
        rep = self._report
        centre = rep.get("sensor_centre_px")
        m = {
            "camera": {
                "focal_px": cam.f, "principal_point_px": [cam.cx, cam.cy],
                "principal_point_from": rep["principal_point_from"],
                "principal_point_minus_sensor_centre_px": (
                    None if centre is None else [cam.cx - centre[0], cam.cy - centre[1]]),
                "time_offset_us": cam.offset_us, "time_offset_from": rep["time_offset_from"],
                "gyro_bias_dps": list(cam.bias_dps), "gyro_bias_from": rep["bias_from"],
                "axis_signs": list(cam.signs), "interpolation": cam.interpolation},
            "calibration": {k: rep[k] for k in ("lead_in_s", "measurements",
                                                "median_normal_error", "estimate")},
            "checks": {"axes": axes, "gravity_roll": rep["gravity_roll"]},
            "bins": {"total": len(rates), **self._bins},
            "events": {"in": self._n_in, "with_truth": self._n_truth, "share_with_truth": share},
            "imu_samples": self._imu_seen,
        }
        self.context.metrics[self.metrics_key("imu_truth")] = m
        for axis, check in axes.items():
            if check.get("sign") == "contradicts":
                self.context.warn(
                    f"{self.id}: the flow turns against the gyro about the camera's {axis} "
                    f"axis (slope {check['slope']:.2f}): the axis sign is wrong; flip it in "
                    "axis_signs")
        grav = rep["gravity_roll"]
        if grav.get("checked") and not 0.9 <= grav["ratio"] <= 1.1:
            self.context.warn(
                f"{self.id}: gravity turned {grav['gravity_turn_deg']:.1f} deg in the image "
                f"plane while the gyro's roll integrates to {grav['gyro_turn_deg']:.1f} deg: "
                "check the roll axis sign and the gyro's full scale")
        if share is not None and share < 0.5:
            b = self._bins
            self.context.warn(
                f"{self.id}: the gyro's flow is the truth for only {100 * share:.1f} % of the "
                f"events: of {len(rates)} bins of {prm.bin_us / 1000:g} ms, {b['disagree']} "
                f"disagree with a pure rotation (camera translation or moving objects), "
                f"{b['few_measurements']} have too few measurements, {b['no_gyro']} no gyro "
                "data; the rest is slower than min_speed_pxs")
