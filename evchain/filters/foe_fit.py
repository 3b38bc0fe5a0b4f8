"""``foe_fit``: the FOE refined from normal-flow magnitudes with a piecewise-planar scene model."""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket
from evchain.core.series import FOE, FOE_VOTES
from evchain.errors import DataError

FOE_DTYPE = FOE.dtype


class FoeFit(Filter):
    """Refines the ``foe`` series of ``foe_map`` by fitting the flow speeds of a road and two
    facades (robust Gauss-Newton; see docs/explanation/foe_ttc.md).

    Under pure translation a road point ``dy`` rows below the FOE (level camera) has inverse
    time to contact ``a0 dy``, a facade point ``dx`` columns beside it ``a1 |dx|`` (left) or
    ``a2 |dx|`` (right), so its normal flow speed is ``(p - foe).n`` times that. Every
    ``estimate_every_us`` the five unknowns are fitted to the flow events of the last
    ``3 tau_ms`` (weights decaying with ``tau_ms``, Tukey on the relative speed residual), from
    the previous fit, else from the latest ``foe_map`` estimate. When the fit fails (singular,
    fewer than ``min_inliers`` decayed inliers, or farther than ``max_deviation_px`` from the
    voting estimate while a fit started from the votes explains more of the flow: a larger
    decayed inlier weight) the voting estimate is emitted and the next fit starts from it again.
    The ``foe_map`` entries move to series ``foe_votes``; series ``foe`` gets one entry per
    fit (t, x, y, support = decayed inlier weight, total = decayed weight of modelled events).

    A fit needs a voting estimate at most ``tau_ms`` old: with none yet, or none for longer
    (``foe_map`` withholds its estimates while the flow's directions agree no better than
    noise would, and the speeds of such flow can still give a fit enough inliers) there is no
    fit and no entry; the fits resume from the last one when voting estimates return.
    ``metrics.foe_fit`` counts the fit times, the fits kept, the voting estimates emitted
    instead, and the times without an estimate.
    """

    name = "foe_fit"
    consumes = FlowPacket
    produces = FlowPacket
    needs_series = (FOE,)
    adds_series = (FOE, FOE_VOTES)

    class Params(FilterParams):
        tau_ms: float = Field(200.0, gt=0, description="decay time constant of the events' "
                              "weights; events older than 3 tau are dropped")
        estimate_every_us: int = Field(10000, ge=1, description="period of the fits")
        margin_px: float = Field(10.0, ge=0, description="events closer than this to a "
                                 "plane's vanishing line (the FOE's row or column) are left "
                                 "out of that plane")
        tolerance: float = Field(0.25, gt=0, description="Tukey constant on the relative "
                                 "speed residual |s - predicted| / predicted (with a looser "
                                 "one an approaching obstacle's lower rows fit the road and "
                                 "pull the FOE up as it fills the view)")
        max_iter: int = Field(4, ge=1, description="Gauss-Newton iterations per fit")
        max_deviation_px: float = Field(40.0, gt=0, description="a fit farther than this "
                                        "from the voting estimate is checked against a fit "
                                        "started from the votes and falls back to them if "
                                        "that one has the larger inlier weight (the votes can "
                                        "err by tens of px for seconds)")
        min_inliers: float = Field(50.0, ge=0, description="fall back when the decayed "
                                   "inlier weight is below this")

    def reset(self) -> None:
        from evchain.kernels import foe_fit as k
        from evchain.kernels.records import record

        p = self.params
        self._prm = record(k.FitParams, margin=p.margin_px, tolerance=p.tolerance,
                           max_iter=p.max_iter, max_step=3.0)
        self._buf = {c: np.zeros(0, np.float64) for c in ("x", "y", "nx", "ny", "s", "e")}
        self._tref = 0  # e = exp((t - tref) / tau): the decay weights, computed once per event
        self._t = np.zeros(0, np.int64)
        self._lo = self._hi = 0  # the buffer's live events: [lo, hi)
        self._next: int | None = None
        self._th = k.initial_theta(math.nan, math.nan)
        self._vote: tuple[int, float, float] | None = None
        self._won = -math.inf  # time a far fit last beat a fit started from the votes
        self._counts = {"fit times": 0, "fits": 0, "votes": 0, "no voting estimate": 0}

    def process(self, packet: FlowPacket) -> FlowPacket:
        if not isinstance(packet, FlowPacket):
            raise DataError(f"foe_fit needs a FlowPacket, got {type(packet).__name__}")
        from evchain.kernels import foe_fit as k

        p = self.params
        period, tau_us = int(p.estimate_every_us), p.tau_ms * 1000.0
        votes = packet.series.get("foe", np.zeros(0, FOE_DTYPE))
        vx, vy = packet.vx.astype(np.float64), packet.vy.astype(np.float64)
        s = np.hypot(vx, vy)
        ok = s > 0
        if packet.t_end - self._tref > 4 * tau_us:  # keep e within exp(+-4) for the window
            tref = packet.t_end - int(2 * tau_us)
            v = self._buf["e"][self._lo:self._hi]
            v *= math.exp(-(tref - self._tref) / tau_us)
            self._tref = tref
        new = {"x": packet.x[ok].astype(np.float64), "y": packet.y[ok].astype(np.float64),
               "nx": vx[ok] / s[ok], "ny": vy[ok] / s[ok], "s": s[ok],
               "e": np.exp((packet.t[ok] - self._tref) / tau_us)}
        self._append(new, packet.t[ok], packet.t_start - int(3 * tau_us))
        buf, t = self._buf, self._t
        if self._next is None:
            self._next = -(-packet.t_start // period) * period
        rows = []
        while self._next < packet.t_end:
            T = self._next
            self._next += period
            j = np.searchsorted(votes["t"], T, side="right")
            if j:
                self._vote = (int(votes["t"][j - 1]), float(votes["x"][j - 1]),
                              float(votes["y"][j - 1]))
            self._counts["fit times"] += 1
            r = None if self._vote is None else self._fit(k, buf, t, T, tau_us)
            if r is None:
                self._counts["no voting estimate"] += 1
                continue
            rows.append((T, *r))
        out = np.zeros(len(rows), FOE_DTYPE)
        for i, r in enumerate(rows):
            out[i] = r
        series = dict(packet.series)
        series["foe_votes"] = votes
        series["foe"] = out
        return packet.replace(series=series)

    def _append(self, new: dict, t_new: np.ndarray, t_keep: int) -> None:
        """Drop events before ``t_keep`` and append the new ones; the arrays grow by doubling and
        are compacted only when full (amortised O(1) per event)."""
        lo, hi, m = self._lo, self._hi, len(t_new)
        lo += int(np.searchsorted(self._t[lo:hi], t_keep))
        if hi + m > len(self._t):
            n = hi - lo
            cap = len(self._t) if 2 * (n + m) <= len(self._t) else max(2 * (n + m), 1024)
            for c, v in self._buf.items():
                w = np.empty(cap, np.float64)
                w[:n] = v[lo:hi]
                self._buf[c] = w
            tt = np.empty(cap, np.int64)
            tt[:n] = self._t[lo:hi]
            self._t = tt
            lo, hi = 0, n
        for c, v in self._buf.items():
            v[hi:hi + m] = new[c]
        self._t[hi:hi + m] = t_new
        self._lo, self._hi = lo, hi + m

    def _fit(self, k, buf, t, T, tau_us):
        """(x, y, support, total) of the fit at T, or the voting estimate's; None when the
        latest voting estimate is older than tau."""
        p = self.params
        t_vote, vx, vy = self._vote
        if T - t_vote > tau_us:  # the flow has shown no FOE for tau: wait, resume from here
            return None
        warm = not math.isnan(self._th[k.FOE_X])
        if not warm:
            self._th = k.initial_theta(vx, vy)
        lo, hi = self._lo, self._hi
        i0 = lo + int(np.searchsorted(t[lo:hi], T - int(3 * tau_us)))
        i1 = lo + int(np.searchsorted(t[lo:hi], T))
        g = math.exp(-(T - self._tref) / tau_us)

        events = k.FitEvents(buf["x"], buf["y"], buf["nx"], buf["ny"], buf["s"], buf["e"])

        def run(th):
            ok, inl, tot = k.fit(events, i0, i1, g, th, self._prm)
            return ok and inl >= p.min_inliers, inl, tot

        th = self._th.copy()
        ok, inl, tot = run(th)
        far = math.hypot(th[k.FOE_X] - vx, th[k.FOE_Y] - vy) > p.max_deviation_px
        if ok and far and warm:
            # Far from the votes: the votes may be the wrong ones (at 15 m/s they err by 30-50 px
            # for seconds). Refit from them; keep the warm fit unless the votes' fit explains
            # more of the flow (larger decayed inlier weight) or the warm fit is the only one.
            # A warm fit that won stays unchallenged for tau (the window's weights change by
            # 1/e), which keeps the extra fits to a few per cent while the votes are off.
            if T - self._won >= tau_us:
                tv = k.initial_theta(vx, vy)
                okv, inlv, _ = run(tv)
                ok = not okv or inl >= inlv
                if ok:
                    self._won = T
        elif ok:
            ok = not far
        if not far:
            self._won = -math.inf
        if ok:
            self._th = th
            self._counts["fits"] += 1
            return th[k.FOE_X], th[k.FOE_Y], inl, tot
        self._th[:] = np.nan
        self._won = -math.inf
        self._counts["votes"] += 1
        return vx, vy, inl, tot

    def flush(self):
        c = self._counts
        self.context.metrics[self.metrics_key("foe_fit")] = {
            "fit_times": c["fit times"], "fits_kept": c["fits"], "voting_estimates": c["votes"],
            "no_estimate": {"no recent voting estimate": c["no voting estimate"]}}
        return None
