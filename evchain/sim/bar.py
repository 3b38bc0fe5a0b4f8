"""The moving-bar stimulus of thesis 4.1, rendered analytically, and its ground truth.

A full-height bar of intensity ``intensity_bar`` over ``intensity_background`` moves right at
``speed_pxs``; its leading edge is at ``x_lead(t) = x0_px + speed_pxs * t`` and its trailing edge
``bar_width_px`` behind. Pixel x (centre at integer x, covering [x - 0.5, x + 0.5]) sees the bar
fraction ``f = P(x_lead - x) - P(x_trail - x)`` where P is the edge's cumulative profile:

* ``sharp``: P(u) = clip(u + 0.5, 0, 1), the exact area of the pixel covered by the bar (box
  filter; no supersampling needed or used);
* ``linear``: a ramp of width w = ``edge_width_px``, P(u) = clip(u / w + 0.5, 0, 1);
* ``sigmoid``: logistic with the ramp's centre slope, P(u) = 1 / (1 + exp(-4 u / w));
* ``erf``: Gaussian blur with sigma = ``edge_width_px``, P(u) = (1 + erf(u / (sigma sqrt 2))) / 2.

Non-sharp profiles are point-sampled at the pixel centre, or averaged over ``supersample``
positions across the pixel. Because P is symmetric, a pixel's intensity rises monotonically
until the bar's centre passes it (``t_mid``) and falls afterwards; the crossing times of any
log level are found by bisection on those two monotone halves (exact to ~1e-9 µs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf


@dataclass(frozen=True)
class Bar:
    width: int = 64
    height: int = 48
    bar_width_px: float = 16.0
    speed_pxs: float = 200.0
    x0_px: float = 0.0
    edge: str = "erf"
    edge_width_px: float = 2.0
    supersample: int = 1
    intensity_bar: float = 1.0
    intensity_background: float = 0.0

    # -- geometry of the motion -----------------------------------------------------------
    def x_lead(self, t_us):
        return self.x0_px + self.speed_pxs * np.asarray(t_us, np.float64) * 1e-6

    def extent_px(self) -> float:
        """Half-width around an edge beyond which its profile is (numerically) flat."""
        w = self.edge_width_px
        return 0.5 + {"sharp": 0.0, "linear": w / 2, "sigmoid": 10 * w / 4, "erf": 6 * w}[
            self.edge]

    def t_mid_us(self, x):
        """When the bar's centre passes pixel column x (the intensity's maximum there)."""
        return (np.asarray(x, np.float64) + self.bar_width_px / 2 - self.x0_px) / \
            self.speed_pxs * 1e6

    # -- rendering --------------------------------------------------------------------------
    def _p(self, u):
        w = self.edge_width_px
        if self.edge == "sharp":
            return np.clip(u + 0.5, 0.0, 1.0)
        if self.edge == "linear":
            return np.clip(u / w + 0.5, 0.0, 1.0)
        if self.edge == "sigmoid":
            return 0.5 * (1.0 + np.tanh(2.0 * u / w))   # = 1 / (1 + exp(-4u/w)), overflow-free
        if self.edge == "erf":
            return 0.5 * (1.0 + erf(u / (w * math.sqrt(2.0))))
        raise ValueError(f"unknown edge {self.edge!r}")

    def fraction(self, x, t_us):
        """Bar coverage fraction f in [0, 1] of pixel column(s) x at time(s) t (broadcast)."""
        x = np.asarray(x, np.float64)
        lead = self.x_lead(t_us)
        trail = lead - self.bar_width_px
        k = 1 if self.edge == "sharp" else self.supersample
        if k == 1:
            return self._p(lead - x) - self._p(trail - x)
        acc = 0.0
        for i in range(k):
            o = (i + 0.5) / k - 0.5
            acc = acc + self._p(lead - (x + o)) - self._p(trail - (x + o))
        return acc / k

    def intensity(self, x, t_us):
        """Linear intensity of pixel column(s) x at time(s) t."""
        f = self.fraction(x, t_us)
        return self.intensity_background + (self.intensity_bar - self.intensity_background) * f

    def render(self, t_us: np.ndarray) -> np.ndarray:
        """Frames float32 [n, H, W] at times t_us."""
        t = np.asarray(t_us, np.float64)
        cols = self.intensity(np.arange(self.width)[None, :], t[:, None]).astype(np.float32)
        return np.ascontiguousarray(np.broadcast_to(cols[:, None, :],
                                                    (len(t), self.height, self.width)))


class BarTruth:
    """Ground truth of a :class:`Bar`: flow (bar velocity on the bar, 0 on the background) and
    exact log-level crossing times for the emulator. A bar translating across the view has no
    FOE and no time to contact, so this truth offers neither (scorers that need them refuse it
    at setup)."""

    def __init__(self, bar: Bar):
        self.bar = bar

    def flow(self, x, y, t_us):
        b = self.bar
        x = np.asarray(x, np.float64)
        lead = b.x_lead(t_us)
        ext = b.extent_px()
        on = (x >= lead - b.bar_width_px - ext) & (x <= lead + ext)
        vx = np.where(on, b.speed_pxs, 0.0)
        return vx, np.zeros_like(vx) + 0.0 * np.asarray(y, np.float64)

    def log_intensity(self, x, t_us, eps: float):
        return np.log(self.bar.intensity(x, t_us) + eps)

    def crossing_times(self, threshold_on, threshold_off, eps: float, t_first_us: float,
                       t_last_us: float, tie_tolerance: float = 1e-6) -> np.ndarray:
        """Exact event times of an ideal emulator (no refractory, no cap, no noise).

        The reference starts at the log intensity at ``t_first_us`` (the first frame);
        thresholds in natural log units, scalars or per-pixel ``[H, W]`` arrays; events up to
        ``t_last_us`` (the last frame). A level counts as reached within ``tie_tolerance``, as
        in the emulator. Returns a structured array (x, y, t float64 µs, p) sorted by pixel
        then time.
        """
        b = self.bar
        scalar = np.ndim(threshold_on) == 0 and np.ndim(threshold_off) == 0
        if scalar:
            xs = np.arange(b.width, dtype=np.float64)
            ys = np.zeros(b.width, np.int64)
            con = np.full(b.width, float(threshold_on))
            coff = np.full(b.width, float(threshold_off))
        else:
            yy, xx = np.mgrid[0:b.height, 0:b.width]
            xs = xx.ravel().astype(np.float64)
            ys = yy.ravel()
            con = np.broadcast_to(threshold_on, (b.height, b.width)).ravel().astype(np.float64)
            coff = np.broadcast_to(threshold_off, (b.height, b.width)).ravel().astype(np.float64)
        t0, t1 = float(t_first_us), float(t_last_us)
        l0 = self.log_intensity(xs, t0, eps)
        tm = np.clip(b.t_mid_us(xs), t0, t1)
        lmax = self.log_intensity(xs, tm, eps)
        lend = self.log_intensity(xs, t1, eps)
        tol = tie_tolerance
        # rising half [t0, tm]: ON levels l0 + n*con reached while level - tol <= lmax
        n_on = np.maximum(np.floor((lmax - l0 + tol) / con).astype(np.int64), 0)
        while True:  # guard the floor against rounding: the last level must be reachable
            bad = (n_on > 0) & (l0 + n_on * con - tol > lmax)
            if not bad.any():
                break
            n_on[bad] -= 1
        # falling half [tm, t1]: OFF levels l0 + n_on*con - m*coff while level + tol >= lend
        ref = l0 + n_on * con
        n_off = np.maximum(np.floor((ref - lend + tol) / coff).astype(np.int64), 0)
        while True:
            bad = (n_off > 0) & (l0 + (n_on * con - n_off * coff) + tol < lend)
            if not bad.any():
                break
            n_off[bad] -= 1
        pix_on = np.repeat(np.arange(len(xs)), n_on)
        k_on = _ranks(n_on)
        lev_on = l0[pix_on] + (k_on * con[pix_on])
        pix_off = np.repeat(np.arange(len(xs)), n_off)
        k_off = _ranks(n_off)
        lev_off = l0[pix_off] + (n_on[pix_off] * con[pix_off] - k_off * coff[pix_off])
        # event time: where the firing rule turns true (L = level -+ tol), as in the emulator
        lev_on = lev_on - tol
        lev_off = lev_off + tol
        t_on = self._bisect(xs[pix_on], lev_on, np.full(len(pix_on), t0), tm[pix_on], eps, True)
        t_off = self._bisect(xs[pix_off], lev_off, tm[pix_off], np.full(len(pix_off), t1), eps,
                             False)
        pix = np.concatenate([pix_on, pix_off])
        t = np.concatenate([t_on, t_off])
        p = np.concatenate([np.ones(len(pix_on), np.int8), -np.ones(len(pix_off), np.int8)])
        order = np.lexsort((t, pix))
        pix, t, p = pix[order], t[order], p[order]
        if scalar:
            # every row of a full-height bar is the same: broadcast the first row
            nrow = len(pix)
            pix = np.tile(pix, b.height)
            y = np.repeat(np.arange(b.height), nrow)
            t = np.tile(t, b.height)
            p = np.tile(p, b.height)
            x = xs[pix].astype(np.int64)
            order = np.lexsort((t, x, y))
            x, y, t, p = x[order], y[order], t[order], p[order]
        else:
            x = xs[pix].astype(np.int64)
            y = ys[pix]
        out = np.zeros(len(t), dtype=[("x", np.int64), ("y", np.int64), ("t", np.float64),
                                      ("p", np.int8)])
        out["x"], out["y"], out["t"], out["p"] = x, y, t, p
        return out

    def _bisect(self, x, level, ta, tb, eps, rising):
        a = ta.astype(np.float64).copy()
        b = tb.astype(np.float64).copy()
        for _ in range(64):
            m = 0.5 * (a + b)
            below = self.log_intensity(x, m, eps) < level
            go_right = below if rising else ~below
            a = np.where(go_right, m, a)
            b = np.where(go_right, b, m)
            if np.all(b - a < 1e-7):
                break
        return 0.5 * (a + b)


def _ranks(counts: np.ndarray) -> np.ndarray:
    """1..counts[i] for each i, concatenated."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    return np.arange(total) - starts + 1
