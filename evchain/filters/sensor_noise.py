"""``sensor_noise``: the background activity and hot pixels of a real DVS, added to events.

A DVS pixel fires without any change of light (docs/explanation/emulator.md, "Sensor noise"):

* **leak events**: junction leakage in the pixel's reset switch slowly moves its memorised
  level, so the pixel fires ON events at a slow, nearly regular rate (v2e: Hu, Liu and
  Delbruck 2021, "v2e: From video frames to realistic DVS events", CVPR workshops, after
  Nozaki and Delbruck 2017, "Temperature and parasitic photocurrent effects in dynamic vision
  sensors", IEEE Trans. Electron Devices). The rate differs from pixel to pixel: v2e draws a
  log-normal factor with a spread of 0.1 decades (``noise_rate_cov_decades``) and jitters the
  leak by 10 % (``leak_jitter_fraction``, there per time step of its frames; here per
  interval); its "noisy" preset uses 0.1 Hz per pixel, about what DAVIS-class sensors show at
  room temperature;
* **shot noise**: photon and transistor noise crossing a threshold, ON and OFF alike, as a
  Poisson process; its rate rises in dim light (v2e's "noisy" preset: 5 Hz per pixel in the
  darkest parts, of order 1 Hz in dim light);
* **hot pixels**: a few defective pixels firing at kHz rates (DAVIS cameras' hardware pixel
  filter learns "the eight most active pixels (above ~5 kHz)": libcaer, ``davis.h``,
  ``DAVIS_CONFIG_DVS_FILTER_PIXEL_AUTO_TRAIN``).

Every process is seeded from the run's seed and its own stream (``context.rng``): turning one
on does not change the events of another. Noise is drawn in fixed blocks of absolute time
(:data:`BLOCK_US`), each from a generator of its own, so where the stream is cut into packets
does not change it; the output is the input merged with the noise by time (at equal times the
input's events come first).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket, Geometry

#: length of the blocks of absolute time in which noise is drawn, µs
BLOCK_US = 100_000
#: shortest leak interval, as a fraction of the pixel's mean interval (jitter never reverses it)
MIN_LEAK_INTERVAL = 0.05


class SensorNoise(Filter):
    """Adds DVS background activity (leak and shot noise) and hot pixels to an event stream.

    Off by default (all rates 0): the packet passes unchanged. Leak: each pixel fires ON events
    at its own rate (the array mean is ``leak_rate_hz``; per pixel a log-normal factor with
    ``leak_spread_decades`` as the standard deviation of its log10, normalised to mean 1), every
    interval jittered by ``leak_jitter`` of the pixel's mean interval, starting at a random
    phase. Shot noise: Poisson events at ``shot_rate_hz`` per pixel, ON and OFF equally likely.
    Hot pixels: ``hot_pixel_fraction`` of the pixels, chosen by the seed, fire Poisson events
    at ``hot_pixel_rate_hz``, ON and OFF equally likely. Rates are constant over the image and
    time (no dependence on intensity or temperature), and noise events do not reset the pixel
    or interact with its signal events.
    """

    name = "sensor_noise"
    consumes = EventPacket
    produces = EventPacket
    sensor = True

    class Params(FilterParams):
        leak_rate_hz: float = Field(0.0, ge=0, le=100, description="mean leak (ON) event rate "
                                    "per pixel, Hz (DAVIS-class at room temperature ~0.1)")
        leak_spread_decades: float = Field(0.1, ge=0, le=0.5, description="pixel-to-pixel spread "
                                           "of the leak rate: standard deviation of its log10 "
                                           "(v2e: 0.1)")
        leak_jitter: float = Field(0.1, ge=0, le=1, description="standard deviation of a leak "
                                   "interval, relative to the pixel's mean interval")
        shot_rate_hz: float = Field(0.0, ge=0, le=100, description="shot-noise events per pixel, "
                                    "Hz, ON and OFF together (dim light: ~1)")
        hot_pixel_fraction: float = Field(0.0, ge=0, le=0.01, description="share of pixels that "
                                          "are hot (0.001 = 0.1 %)")
        hot_pixel_rate_hz: float = Field(1000.0, gt=0, le=10_000, description="event rate of a "
                                         "hot pixel, Hz, ON and OFF together")

    @property
    def active(self) -> bool:
        p = self.params
        return p.leak_rate_hz > 0 or p.shot_rate_hz > 0 or p.hot_pixel_fraction > 0

    def reset(self) -> None:
        self._geometry: Geometry | None = None
        self._block = -1                         # index of the last block drawn
        self._noise = _empty()                   # its events (t, x, y, p), time-ordered
        self._origin = 0                         # the stream's first time: no noise before
        self.hot_pixels = np.zeros(0, np.int64)  # flat indices y * width + x, once set up
        self.leak_rates_hz = np.zeros(0)         # per pixel (flat), once set up

    # -- per-pixel properties, fixed by the seed at the first packet ---------------------------
    def _init(self, packet: EventPacket) -> None:
        g = packet.geometry
        npix = g.width * g.height
        p = self.params
        self._geometry = g
        self._origin = packet.t_start
        self._block = packet.t_start // BLOCK_US - 1
        if p.leak_rate_hz > 0:
            s = p.leak_spread_decades * math.log(10.0)    # sigma of the natural log
            z = self.context.rng(f"{self.id}/leak_rates").standard_normal(npix)
            self.leak_rates_hz = p.leak_rate_hz * np.exp(s * z - 0.5 * s * s)   # mean 1
            self._leak_period_us = 1e6 / self.leak_rates_hz
            phase = self.context.rng(f"{self.id}/leak_phase").random(npix)
            self._leak_next = (self._block + 1) * BLOCK_US + phase * self._leak_period_us
        n_hot = round(p.hot_pixel_fraction * npix)
        if n_hot:
            rng = self.context.rng(f"{self.id}/hot_pixels")
            self.hot_pixels = np.sort(rng.choice(npix, n_hot, replace=False)).astype(np.int64)

    # -- one block of noise --------------------------------------------------------------------
    def _draw_block(self, b: int) -> tuple[np.ndarray, ...]:
        """The noise events of block ``b`` ([b, b + 1) * BLOCK_US), time-ordered (ties: leak,
        shot, hot, each in the order drawn). Blocks must be drawn in order (the leak's state)."""
        p = self.params
        g = self._geometry
        npix = g.width * g.height
        b0, b1 = b * BLOCK_US, (b + 1) * BLOCK_US
        dt_s = BLOCK_US * 1e-6
        parts_t, parts_i, parts_p = [], [], []
        if p.leak_rate_hz > 0:
            rng = self.context.rng(f"{self.id}/leak/{b}")
            nxt, period = self._leak_next, self._leak_period_us
            idx = np.flatnonzero(nxt < b1)
            while idx.size:
                parts_t.append(np.floor(nxt[idx]).astype(np.int64))
                parts_i.append(idx)
                parts_p.append(np.ones(idx.size, np.int8))
                step = np.maximum(1.0 + p.leak_jitter * rng.standard_normal(idx.size),
                                  MIN_LEAK_INTERVAL)
                nxt[idx] += period[idx] * step
                idx = idx[nxt[idx] < b1]
        if p.shot_rate_hz > 0:
            rng = self.context.rng(f"{self.id}/shot/{b}")
            n = int(rng.poisson(p.shot_rate_hz * npix * dt_s))
            parts_i.append(rng.integers(0, npix, n))
            parts_t.append(rng.integers(b0, b1, n))
            parts_p.append(_polarities(rng, n))
        if len(self.hot_pixels):
            rng = self.context.rng(f"{self.id}/hot/{b}")
            counts = rng.poisson(p.hot_pixel_rate_hz * dt_s, len(self.hot_pixels))
            n = int(counts.sum())
            parts_i.append(np.repeat(self.hot_pixels, counts))
            parts_t.append(rng.integers(b0, b1, n))
            parts_p.append(_polarities(rng, n))
        if not parts_t:
            return _empty()
        t = np.concatenate(parts_t)
        i = np.concatenate(parts_i)
        pol = np.concatenate(parts_p)
        order = np.argsort(t, kind="stable")
        i = i[order]
        return (t[order], (i % g.width).astype(np.uint16), (i // g.width).astype(np.uint16),
                pol[order])

    def _noise_in(self, t0: int, t1: int) -> tuple[np.ndarray, ...]:
        """The noise events in ``[t0, t1)`` (the packets' slices follow each other)."""
        t0 = max(t0, self._origin)
        if t1 <= t0:
            return _empty()
        out = []
        while True:
            t, x, y, pol = self._noise
            a = np.searchsorted(t, t0, side="left")
            z = np.searchsorted(t, t1, side="left")
            if z > a:
                out.append((t[a:z], x[a:z], y[a:z], pol[a:z]))
            if (self._block + 1) * BLOCK_US >= t1:
                break
            self._block += 1
            self._noise = self._draw_block(self._block)
        if not out:
            return _empty()
        if len(out) == 1:
            return out[0]
        return tuple(np.concatenate(cols) for cols in zip(*out, strict=True))

    def process(self, packet: EventPacket) -> EventPacket:
        if not self.active:
            return packet
        if self._geometry is None:
            self._init(packet)
        nt, nx, ny, npol = self._noise_in(packet.t_start, packet.t_end)
        m = len(nt)
        if m == 0 and type(packet) is EventPacket:
            return packet
        n = len(packet)
        # merge by time; at equal times the input's events first
        at = np.searchsorted(packet.t, nt, side="right") + np.arange(m)
        is_noise = np.zeros(n + m, np.bool_)
        is_noise[at] = True
        cols = {}
        for name, mine, dtype in (("x", nx, np.uint16), ("y", ny, np.uint16),
                                  ("t", nt, np.int64), ("p", npol, np.int8)):
            col = np.empty(n + m, dtype)
            col[at] = mine
            col[~is_noise] = getattr(packet, name)
            cols[name] = col
        return EventPacket(geometry=packet.geometry, t_start=packet.t_start,
                           t_end=packet.t_end, series=packet.series, **cols)


def _polarities(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)


def _empty() -> tuple[np.ndarray, ...]:
    return (np.zeros(0, np.int64), np.zeros(0, np.uint16), np.zeros(0, np.uint16),
            np.zeros(0, np.int8))
