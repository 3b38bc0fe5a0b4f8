"""``aps``: DAVIS-like intensity frames (APS) from the scene's linear frames.

See ``docs/explanation/frames.md`` for the model and its limits.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import ApsFramePacket, FramePacket, Geometry
from evchain.errors import DataError

#: APS dynamic range of the DAVIS240 in dB (Brandli et al. 2014, abstract)
DAVIS240_APS_DR_DB = 51.0
#: assumed full well (electrons); the paper gives the dynamic range, not the well
DAVIS240_FULL_WELL_E = 10_000.0


class Aps(Filter):
    """DAVIS-like frames: each exposure window averaged over time, then electrons, noise, ADC.

    Frame n's exposure starts at ``n / rate_hz`` (row r's ``r * row_time_us`` later with a
    rolling shutter) and lasts ``exposure_us``. The input frames are samples of the linear
    intensity at their times; between two samples the intensity is taken as linear in time, and
    each pixel's exposure is its exact time average over the window (motion blur; the
    ``scene`` source renders a frame whenever any pixel has moved ``max_motion_px``, so the
    samples are dense enough). The average times ``gain_e_per_unit`` gives the expected
    electrons; ``shot_noise`` draws them from a Poisson law, ``read_noise_e`` adds Gaussian read
    noise, the result is clipped to ``[0, full_well_e]`` and quantised by an ``adc_bits`` ADC
    whose full scale is the full well (round to nearest). Output frames are the digital numbers
    as a fraction of full scale (``DN / (2^bits - 1)``), at the time each frame's exposure ended
    (``t``; ``t_exposure_start`` when it began). A frame leaves once an input frame at or after
    its end has arrived, so output slices lag; windows that start before the first input frame
    or end after the last are not emitted. Noise is drawn from ``context.rng`` (the run's seed
    and the stage's id), frame by frame.

    Defaults (a DAVIS240C): Brandli et al., "A 240x180 130 dB 3 us latency global shutter
    spatiotemporal vision sensor", IEEE J. Solid-State Circuits 49(10), 2014, report a 51 dB
    APS dynamic range (and 0.5 % fixed-pattern noise, not modelled); the DAVIS240's APS ADC has
    10 bits; libcaer's default APS exposure is 4 ms at a 40 ms frame interval (25 fps). The
    paper gives no full well: 10 000 e- is assumed, and the read noise is set so that full well
    / read noise is the paper's 51 dB (28 e-). The gain fills the well at intensity 1 (the
    scene's white). Ideal frames (the frame baseline's "ideal 8-bit camera"):
    ``shot_noise: false, read_noise_e: 0, adc_bits: 8``.
    """

    name = "aps"
    consumes = FramePacket
    produces = ApsFramePacket
    sensor = True

    class Params(FilterParams):
        rate_hz: float = Field(25.0, gt=0, le=100_000, description="frames per second (frame "
                               "n's exposure starts at n / rate_hz)")
        exposure_us: float = Field(4000.0, gt=0, description="exposure time of each row, µs "
                                   "(at most one frame interval)")
        shutter: Literal["global", "rolling"] = Field(
            "global", description="global: every row exposed together; rolling: row r's window "
            "starts r * row_time_us later")
        row_time_us: float | None = Field(None, ge=0, description="rolling shutter: offset "
                                          "between consecutive rows' windows, µs")
        gain_e_per_unit: float = Field(DAVIS240_FULL_WELL_E, gt=0, description="expected "
                                       "electrons per exposure at linear intensity 1")
        full_well_e: float = Field(DAVIS240_FULL_WELL_E, gt=0, description="full well, "
                                   "electrons: the clip level and the ADC's full scale")
        read_noise_e: float = Field(
            round(DAVIS240_FULL_WELL_E / 10 ** (DAVIS240_APS_DR_DB / 20), 1), ge=0,
            description="Gaussian read noise, electrons rms (0: none)")
        shot_noise: bool = Field(True, description="Poisson shot noise on the electrons")
        adc_bits: int = Field(10, ge=1, le=16, description="ADC resolution, bits")

        @model_validator(mode="after")
        def _check(self):
            if self.exposure_us > 1e6 / self.rate_hz:
                raise ValueError(f"exposure_us {self.exposure_us} exceeds the frame interval "
                                 f"1e6 / rate_hz = {1e6 / self.rate_hz:g} us")
            if self.shutter == "rolling" and self.row_time_us is None:
                raise ValueError("a rolling shutter needs row_time_us")
            return self

    def reset(self) -> None:
        self._geometry: Geometry | None = None
        self._prev: tuple[int, np.ndarray] | None = None  # last input frame (t, frame)
        self._next_n: int | None = None                   # next exposure to open
        self._open: list[dict] = []                        # exposures being integrated
        self._out_end: int | None = None
        self._last_end: int | None = None
        self._rng = self.context.rng(f"{self.id}/noise")

    # -- exposure windows --------------------------------------------------------------------
    def start_us(self, n: int) -> float:
        """Start of frame n's exposure (its first row), µs."""
        return n * 1e6 / self.params.rate_hz

    def _row_offsets(self) -> np.ndarray | float:
        p = self.params
        if p.shutter == "global":
            return 0.0
        return np.arange(self._geometry.height, dtype=np.float64) * float(p.row_time_us)

    def _open_window(self, n: int) -> dict:
        s = self.start_us(n)
        lo = s + self._row_offsets()
        hi = lo + self.params.exposure_us
        return {"n": n, "lo": lo, "hi": hi, "end": float(np.max(hi)),
                "acc": np.zeros(self._geometry.shape, np.float64)}

    # -- streaming ---------------------------------------------------------------------------
    def process(self, packet: FramePacket) -> ApsFramePacket:
        if self._geometry is None:
            self._geometry = packet.geometry
            self._out_end = packet.t_start
        elif packet.geometry != self._geometry:
            raise DataError(f"aps: sensor geometry changed from {self._geometry} to "
                            f"{packet.geometry}")
        frames, times, starts = [], [], []
        for t, frame in zip(packet.t.tolist(), packet.frames, strict=True):
            self._add(int(t), frame, frames, times, starts)
        self._last_end = packet.t_end
        end = self._out_end
        if self._prev is not None:
            end = max(end, min(packet.t_end, self._prev[0] + 1))
        return self._packet(frames, times, starts, end)

    def flush(self) -> ApsFramePacket | None:
        if self._geometry is None:
            return None
        return self._packet([], [], [], max(self._out_end, self._last_end))

    def _packet(self, frames, times, starts, end: int) -> ApsFramePacket:
        g = self._geometry
        out = ApsFramePacket(geometry=g, t_start=self._out_end, t_end=end,
                             frames=(np.stack(frames) if frames
                                     else np.zeros((0, *g.shape), np.float32)),
                             t=np.array(times, np.int64), t_exposure_start=np.array(starts,
                                                                                    np.int64))
        self._out_end = end
        return out

    def _add(self, t: int, frame: np.ndarray, frames, times, starts) -> None:
        """Integrate the interval from the previous input frame to this one into the open
        exposures; close those that end by ``t``."""
        if self._prev is None:
            # the first exposure that starts at or after the first input frame
            n = math.ceil(t * self.params.rate_hz / 1e6)
            while self.start_us(n) < t:
                n += 1
            while n > 0 and self.start_us(n - 1) >= t:
                n -= 1
            self._next_n = n
            self._prev = (t, frame)
            return
        ta, fa = self._prev
        while self.start_us(self._next_n) < t:
            self._open.append(self._open_window(self._next_n))
            self._next_n += 1
        for w in self._open:
            wa, wb = interval_weights(ta, t, w["lo"], w["hi"])
            if np.any(wa) or np.any(wb):
                if np.ndim(wa):
                    w["acc"] += wa[:, None] * fa + wb[:, None] * frame
                else:
                    w["acc"] += wa * fa + wb * frame
        while self._open and self._open[0]["end"] <= t:
            w = self._open.pop(0)
            frames.append(self._read_out(w["acc"] / self.params.exposure_us))
            times.append(math.ceil(w["end"]))
            starts.append(math.floor(float(np.min(w["lo"]))))
        self._prev = (t, frame)

    def _read_out(self, mean_intensity: np.ndarray) -> np.ndarray:
        """Electrons, noise, clipping and the ADC: the frame as a fraction of full scale."""
        p = self.params
        electrons = np.maximum(mean_intensity, 0.0) * p.gain_e_per_unit
        if p.shot_noise:
            electrons = self._rng.poisson(electrons).astype(np.float64)
        if p.read_noise_e > 0:
            electrons = electrons + self._rng.normal(0.0, p.read_noise_e, electrons.shape)
        levels = (1 << p.adc_bits) - 1
        dn = np.floor(np.clip(electrons, 0.0, p.full_well_e) / p.full_well_e * levels + 0.5)
        return (dn / levels).astype(np.float32)


def interval_weights(ta: float, tb: float, lo, hi):
    """Weights (wa, wb) such that ``wa * I(ta) + wb * I(tb)`` is the integral over
    ``[ta, tb] ∩ [lo, hi]`` of the intensity linear in time between the samples at ``ta`` and
    ``tb`` (µs; ``lo``, ``hi`` scalars or one per row)."""
    u = np.maximum(ta, lo)
    v = np.minimum(tb, hi)
    ok = v > u
    dt = float(tb - ta)
    u = np.where(ok, u, 0.0)
    v = np.where(ok, v, 0.0)
    wa = np.where(ok, ((tb - u) ** 2 - (tb - v) ** 2) / (2.0 * dt), 0.0)
    wb = np.where(ok, ((v - ta) ** 2 - (u - ta) ** 2) / (2.0 * dt), 0.0)
    return wa, wb
