"""DVS emulator: frames of linear intensity in, events at interpolated crossing times out.

See ``docs/explanation/emulator.md`` for the model, the tie rule, the ordering of events and
the measured timing error of the two interpolations.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, FramePacket, Geometry
from evchain.errors import DataError

#: the thesis's 8-bit log scale: Lg = 255 * ln(1 + g) / ln(256) for grey g in [0, 255]
THESIS8BIT_UNIT = math.log(256.0) / 255.0
#: relative threshold floor after mismatch (a threshold is never <= 0)
MISMATCH_FLOOR = 0.01


class Emulator(Filter):
    """DVS emulator: events where log intensity crosses per-pixel levels, at interpolated times.

    L = ln(I + eps) per pixel; the reference starts at the first frame; each crossing of
    L_ref + threshold_on (ON) or L_ref - threshold_off (OFF) emits one event and moves L_ref by
    one threshold. Crossing times come from a linear or a monotone cubic interpolation of L
    between frames; an interval's events leave when its end frame arrives (the cubic needs one
    more frame of look-ahead), so output slices lag. Events are time-ordered; times are rounded
    to the nearest µs (set ``record_float_times = True`` before setup to keep the float times
    in ``float_times``). The input's series (e.g. the scene's simulated IMU) pass on, each
    entry with the output slice that holds it.
    """

    name = "emulator"
    consumes = FramePacket
    produces = EventPacket
    sensor = True
    #: most pixels per strip of the event loop (default ``emulator_state.STRIP``; the image is
    #: cut into strips of equal length, whole chunks of 64); the events do not depend on it
    strip_pixels: int | None = None
    #: frame intervals run strip by strip at a time (default ``emulator_state.BLOCK``)
    block_intervals: int | None = None

    class Params(FilterParams):
        threshold_on: float = Field(0.2, gt=0, description="ON threshold, natural log units "
                                    "(or on the 0..255 scale with log_mapping=thesis8bit)")
        threshold_off: float = Field(0.2, gt=0, description="OFF threshold, same units")
        eps: float = Field(1e-3, gt=0, description="L = ln(I + eps); ignored with thesis8bit "
                           "(which implies eps = 1/255 of full scale I = 1)")
        log_mapping: Literal["natural", "thesis8bit"] = Field(
            "natural", description="natural: thresholds in ln units; thesis8bit: grey 255*I "
            "mapped to 255*ln(1+g)/ln(256), thresholds given on that scale (thesis 10/20/40)")
        interpolation: Literal["cubic", "linear"] = Field(
            "cubic", description="L between frames: monotone cubic Hermite through the "
            "neighbouring frames (one frame look-ahead) or linear")
        mismatch_sigma: float = Field(0.0, ge=0, le=0.5, description="relative Gaussian "
                                      "threshold mismatch per pixel (real DVS ~0.021); "
                                      "clipped at 1 % of the nominal threshold")
        refractory_us: float = Field(0.0, ge=0, description="an event less than this after the "
                                     "pixel's last emitted event is dropped (reference moves)")
        max_events_per_interval: int | None = Field(
            None, ge=1, description="cap on crossings per pixel per frame interval (thesis: 5); "
            "the rest carries over to the next interval")
        noise_rate_hz: float = Field(0.0, ge=0, description="Poisson background events per "
                                     "pixel per second (random polarity), off by default")
        tie_tolerance: float = Field(1e-6, ge=0, le=1e-2, description="L within this of a "
                                     "level (ln units) counts as reaching it")

    def natural_parameters(self) -> tuple[float, float, float]:
        """(threshold_on, threshold_off, eps) in natural log units: what the kernel uses."""
        p = self.params
        if p.log_mapping == "thesis8bit":
            return (p.threshold_on * THESIS8BIT_UNIT, p.threshold_off * THESIS8BIT_UNIT,
                    1.0 / 255.0)
        return p.threshold_on, p.threshold_off, p.eps

    def reset(self) -> None:
        self._geometry: Geometry | None = None
        self._state = None
        self._held = None            # last <= 3 frames, float32 [h, H, W]
        self._held_t = np.zeros(0, np.int64)
        self._seen = 0               # frames seen
        self._next_j = 0             # next interval (global index of its first frame)
        self._out_end: int | None = None
        self._last_t_end: int | None = None
        self._carry = None           # events at the slice end, held for the next output
        self._series: dict[str, np.ndarray] = {}   # input series entries not yet sent
        self._cap_hint = 4096
        self.float_times: list[np.ndarray] | None = [] if getattr(self, "record_float_times",
                                                                  False) else None
        seed_base = f"{getattr(self, 'id', self.name)}"
        ctx = getattr(self, "context", None)
        if ctx is not None:
            self._rng_mismatch = ctx.rng(seed_base + "/mismatch")
            self._rng_noise = [ctx.rng(seed_base + f"/noise/{k}") for k in range(4)]

    # -- state -------------------------------------------------------------------------------
    def _init(self, packet: FramePacket) -> None:
        from evchain.kernels import emulator_state as K

        g = packet.geometry
        h, w = g.height, g.width
        frames = packet.frames
        if frames.ndim != 3 or frames.shape[1:] != (h, w):
            raise DataError(f"emulator input: frames must have shape [n, {h}, {w}], got "
                            f"{frames.shape}")
        c_on, c_off, eps = self.natural_parameters()
        sigma = self.params.mismatch_sigma
        npix = h * w
        con = np.array([c_on], np.float64)       # one row of thresholds for all pixels
        coff = np.array([c_off], np.float64)
        if sigma > 0:
            con = c_on * np.maximum(1.0 + sigma * self._rng_mismatch.standard_normal(npix),
                                    MISMATCH_FLOOR)
            coff = c_off * np.maximum(1.0 + sigma * self._rng_mismatch.standard_normal(npix),
                                      MISMATCH_FLOOR)
        thr = K.threshold_rows(con, coff)
        # all per-pixel state touched on events lives in one 64-byte row per pixel (array
        # of structs, rows aligned to 64 bytes): an event visit touches one cache line
        # instead of one line per array. A chunk's rows are filled when the scan first finds
        # a candidate in it, so set-up writes only the gates
        row = K.ROW
        buf = np.empty(npix * row + row)
        off = (-buf.ctypes.data % (row * 8)) // 8
        aos = buf[off:off + npix * row].reshape(npix, row)
        counts = aos.view(np.int32)
        st = {"hi": np.empty(npix, np.float32), "lo": np.empty(npix, np.float32),
              "first": np.empty(npix, np.float32), "thr": thr,
              "ready": np.zeros(-(-npix // K.CHUNK) + 1, np.int64)}
        # the kernel reads the rows whole (one 2-D array: one address computation per pixel
        # for all fields, instead of one per strided view)
        self._rows, self._counts = aos, counts
        first = np.ascontiguousarray(frames[0], dtype=np.float32)
        p = self.params
        rule = K.make_rule(p.interpolation == "cubic", eps, p.tie_tolerance,
                           float(p.refractory_us), -1)    # init_gates reads eps and the gates
        err, y, x = K.init_gates(first, rule, self._pixels(st))
        self._raise_pixel(err, packet, 0, y, x)
        self._geometry = g
        self._state = st
        self._eps = eps
        self._held = np.zeros((0, h, w), np.float32)
        self._strip = K.strip_length(npix, self.strip_pixels or K.STRIP)
        self._scratch = K.new_scratch(self._strip, 4096)

    @property
    def thresholds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Per-pixel (ON, OFF) thresholds in natural log units, once the first frame is seen."""
        if self._state is None:
            return None
        shape = self._geometry.shape
        thr = self._state["thr"]
        return (np.broadcast_to(thr[:, 0], (shape[0] * shape[1],)).reshape(shape),
                np.broadcast_to(thr[:, 1], (shape[0] * shape[1],)).reshape(shape))

    def _pixels(self, st):
        from evchain.kernels.emulator_state import Pixels

        return Pixels(self._rows, self._counts, st["hi"], st["lo"], st["first"], st["thr"],
                      st["ready"])

    @staticmethod
    def _raise_pixel(err: int, packet: FramePacket, index: int, y: int, x: int) -> None:
        if err == 0:
            return
        what = "not finite (NaN or inf)" if err == 1 else "negative"
        t = int(packet.t[index]) if 0 <= index < len(packet.t) else None
        raise DataError(f"emulator input: frame {index} of the packet [{packet.t_start}, "
                        f"{packet.t_end}) us (t={t} us) is {what} at pixel (x={x}, y={y}); "
                        "frames must be finite linear intensity >= 0")

    # -- processing --------------------------------------------------------------------------
    def process(self, packet: FramePacket) -> EventPacket:
        if self._out_end is None:
            self._out_end = packet.t_start
        self._last_t_end = packet.t_end
        for name, entries in packet.series.items():   # e.g. a simulated IMU: passed on
            held = self._series.get(name)
            self._series[name] = entries if held is None else np.concatenate([held, entries])
        n = len(packet.t)
        if n == 0:
            return self._emit(self._out_end, final=False, geometry=packet.geometry)
        if self._state is None:
            self._init(packet)
        frames = packet.frames
        g = self._geometry
        if frames.ndim != 3 or frames.shape[1:] != g.shape:
            raise DataError(f"emulator input: frames must have shape [n, {g.height}, {g.width}] "
                            f"like the first packet, got {frames.shape} in the packet "
                            f"[{packet.t_start}, {packet.t_end}) us")
        t = np.asarray(packet.t, np.int64)
        prev_t = self._held_t[-1] if len(self._held_t) else None
        if (prev_t is not None and t[0] <= prev_t) or (n > 1 and np.any(np.diff(t) <= 0)):
            allt = np.concatenate([self._held_t[-1:], t])
            i = int(np.argmax(np.diff(allt) <= 0))
            raise DataError(f"emulator input: frame times must increase; in the packet "
                            f"[{packet.t_start}, {packet.t_end}) us a frame at {allt[i + 1]} us "
                            f"follows one at {allt[i]} us")
        if frames.dtype != np.float32 or not frames.flags.c_contiguous:
            frames = np.ascontiguousarray(frames, dtype=np.float32)
        cubic = self.params.interpolation == "cubic"
        seen_new = self._seen + n
        last_j = seen_new - (3 if cubic else 2)   # last interval that can be done now
        self._run(frames, t, seen_new, last_j + 1, packet)
        # keep the last three frames for the next packet
        if n >= 3:
            # into the same buffer each time (a fresh copy costs page faults)
            if self._held.shape[0] != 3:
                self._held = np.empty((3, *g.shape), np.float32)
            np.copyto(self._held, frames[-3:])
            self._held_t = t[-3:].copy()
        else:
            self._held = np.concatenate([self._held, frames])[-3:]
            self._held_t = np.concatenate([self._held_t, t])[-3:]
        self._seen = seen_new
        k = self._next_j - (seen_new - len(self._held_t))
        end = int(self._held_t[k]) if 0 <= k < len(self._held_t) else self._out_end
        end = max(end, self._out_end)
        return self._emit(end, final=False, geometry=packet.geometry)

    def _run(self, frames, t, seen_new, j_stop, packet) -> None:
        """Process intervals ``self._next_j .. j_stop - 1`` (global indices)."""
        from evchain.kernels import emulator_state as K
        from evchain.kernels.emulator import emulate
        from evchain.kernels.emulator_state import FrameList, Noise, make_rule

        if j_stop <= self._next_j:
            return
        nh = len(self._held)
        base = self._seen - nh           # global index of held[0]
        times = np.concatenate([self._held_t, t])
        j0 = self._next_j - base
        j1 = j_stop - base
        if j0 < 0:
            raise RuntimeError("emulator: internal error, a needed frame was dropped")
        nf = self._noise(times, j0, j1)
        st = self._state
        p = self.params
        cap = -1 if p.max_events_per_interval is None else p.max_events_per_interval
        cubic = p.interpolation == "cubic"
        total = nh + len(t)
        keep_tf = self.float_times is not None
        if self._carry is None:
            e16 = np.zeros(0, np.uint16)
            carry = (e16, e16, np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int8))
        else:
            cx, cy, ct, cp, ctf = self._carry
            carry = (cx, cy, ct, ctf, cp)
        rule = make_rule(cubic, self._eps, p.tie_tolerance, float(p.refractory_us), cap,
                         self._strip, self.block_intervals or K.BLOCK)
        try:
            x, y, tt, tf, pol, n, err, ef, ey, ex, self._scratch = emulate(
                FrameList(self._held, frames, times, base, total), j0, j1, rule,
                self._pixels(st), Noise(*nf), self._cap_hint,
                carry, keep_tf, self._scratch)
        except OverflowError as e:
            raise DataError(f"emulator input: in the packet [{packet.t_start}, "
                            f"{packet.t_end}) us, {e}") from None
        if err:
            self._raise_pixel(err, packet, ef - nh, ey, ex)
        self._cap_hint = max(4096, int((n - len(carry[0])) * 1.25))
        self._next_j = j_stop
        # the kernel put the held events first: no concatenation here
        self._carry = (x[:n], y[:n], tt[:n], pol[:n], tf[:n] if keep_tf else tf)

    def _noise(self, times, j0, j1):
        """Background noise events of intervals j0..j1-1 (kernel arrays)."""
        rate = self.params.noise_rate_hz
        k = j1 - j0
        off = np.zeros(k + 1, np.int64)
        if rate <= 0 or k <= 0:
            e16 = np.zeros(0, np.uint16)
            return off, e16, e16, np.zeros(0), np.zeros(0, np.int8)
        g = self._geometry
        npix = g.width * g.height
        dt = np.diff(times[j0:j1 + 1]).astype(np.float64)
        r_count, r_pix, r_t, r_p = self._rng_noise
        counts = r_count.poisson(rate * npix * dt * 1e-6)
        off[1:] = np.cumsum(counts)
        m = int(off[-1])
        pix = r_pix.integers(0, npix, m)
        frac = r_t.random(m)
        pol = np.where(r_p.random(m) < 0.5, 1, -1).astype(np.int8)
        t0 = np.repeat(times[j0:j1].astype(np.float64), counts)
        tn = t0 + frac * np.repeat(dt, counts)
        return (off, (pix // g.width).astype(np.uint16), (pix % g.width).astype(np.uint16),
                tn, pol)

    def _emit(self, end: int, final: bool, geometry: Geometry) -> EventPacket:
        start = self._out_end
        ev = self._carry
        if ev is None or len(ev[0]) == 0:
            out_ev = None
            self._carry = None
        elif final:
            out_ev, self._carry = ev, None
        else:
            k = int(np.searchsorted(ev[2], end, side="left"))
            out_ev = tuple(a[:k] for a in ev)
            self._carry = tuple(a[k:] for a in ev) if k < len(ev[0]) else None
        self._out_end = end
        if out_ev is None:
            out = EventPacket.empty(geometry, start, end)
        else:
            if self.float_times is not None:
                self.float_times.append(out_ev[4])
            out = EventPacket(geometry=geometry, t_start=start, t_end=end, x=out_ev[0],
                              y=out_ev[1], t=out_ev[2], p=out_ev[3])
        return self._with_series(out, final)

    def _with_series(self, out: EventPacket, final: bool) -> EventPacket:
        """``out`` with the input's series entries of its slice (all that are left at the
        end); the output lags the input, so entries wait for the slice that holds them."""
        if not self._series:
            return out
        series = {}
        for name, entries in self._series.items():
            n = len(entries) if final else int(np.searchsorted(entries["t"], out.t_end))
            series[name] = entries[:n]
            self._series[name] = entries[n:]
        return out.replace(series=series)

    def flush(self) -> EventPacket | None:
        if self._out_end is None:
            return None
        if self._state is not None and self._seen >= 2:
            # the cubic's last interval, without look-ahead (secant slope at the end)
            empty = np.zeros((0, *self._geometry.shape), np.float32)
            fake = FramePacket.empty(self._geometry, self._last_t_end, self._last_t_end)
            self._run(empty, np.zeros(0, np.int64), self._seen, self._seen - 1, fake)
        geometry = self._geometry or Geometry(1, 1)
        if self._geometry is None:
            return None
        end = max(self._last_t_end, self._out_end)
        return self._emit(end, final=True, geometry=geometry)
