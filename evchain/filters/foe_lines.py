"""``foe_lines``: the FOE from full flow, where the flow vectors' lines meet (frame baseline)."""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket
from evchain.core.series import FOE
from evchain.errors import DataError


class FoeLines(Filter):
    """FOE from full flow: the point the flow vectors' lines pass through (RANSAC, then
    iteratively reweighted least squares).

    Under forward translation every full-flow vector points away from the FOE, so the FOE lies
    on the line through its pixel along it. Every ``estimate_every_us`` the flow events of the
    last ``window_ms`` (at least ``min_speed_pxs``) are fitted: ``ransac_hypotheses``
    intersections of random pairs of lines (and the previous estimate) are scored on up to
    ``ransac_sample`` events by how many point away from them within ``tolerance_deg``; the best
    is refined by least squares on every event, each weighted by Tukey's biweight of its
    angular residual (``tolerance_deg``) over its squared distance from the estimate, so that
    the residual is an angle. Events nearer the estimate than ``min_distance_px`` are left out.
    Fewer than ``min_inliers`` inliers: no estimate at that tick. Series ``foe``: t, x, y,
    support = inliers, total = events fitted. This filter is for full flow (``frame_flow``);
    normal flow does not point away from the FOE (use ``foe_map`` and ``foe_fit``).
    """

    name = "foe_lines"
    consumes = FlowPacket
    produces = FlowPacket
    adds_series = (FOE,)

    class Params(FilterParams):
        estimate_every_us: int = Field(10_000, ge=1, description="period of the estimates")
        window_ms: float = Field(100.0, gt=0, description="flow events of this last stretch "
                                 "are fitted")
        min_speed_pxs: float = Field(1.0, ge=0, description="slower flow is left out (its "
                                     "direction is unreliable)")
        tolerance_deg: float = Field(3.0, gt=0, lt=90, description="angular residual: RANSAC "
                                     "inlier threshold and Tukey constant")
        min_distance_px: float = Field(5.0, ge=0, description="events this close to the "
                                       "estimate are left out (their angle is ill-defined)")
        ransac_hypotheses: int = Field(64, ge=1, description="pairs of lines tried")
        ransac_sample: int = Field(2000, ge=10, description="events the hypotheses are "
                                   "scored on")
        max_iter: int = Field(8, ge=1, description="reweighted least-squares iterations")
        min_inliers: int = Field(50, ge=2, description="fewer inliers: no estimate")

    def reset(self) -> None:
        self._cols: dict[str, np.ndarray] = {k: np.zeros(0) for k in ("x", "y", "vx", "vy")}
        self._t = np.zeros(0, np.int64)
        self._next: int | None = None
        self._last: tuple[float, float] | None = None
        self._fitted: tuple[int, int] | None = None   # (first, last) event time of the last fit
        self._rng = self.context.rng(f"{self.id}/ransac")

    def process(self, packet: FlowPacket) -> FlowPacket:
        if not isinstance(packet, FlowPacket):
            raise DataError(f"foe_lines needs a FlowPacket, got {type(packet).__name__}")
        p = self.params
        period, window = int(p.estimate_every_us), int(p.window_ms * 1000)
        keep = np.hypot(packet.vx, packet.vy) >= max(p.min_speed_pxs, 1e-12)
        t_new = packet.t[keep]
        cut = int(np.searchsorted(self._t, packet.t_start - window))
        self._t = np.concatenate([self._t[cut:], t_new])
        for k in self._cols:
            self._cols[k] = np.concatenate([self._cols[k][cut:],
                                            getattr(packet, k)[keep].astype(np.float64)])
        if self._next is None:
            self._next = -(-packet.t_start // period) * period
        rows = []
        while self._next < packet.t_end:
            T = self._next
            self._next += period
            i0 = int(np.searchsorted(self._t, T - window))
            i1 = int(np.searchsorted(self._t, T))
            if i1 - i0 < p.min_inliers:
                continue
            span = (int(self._t[i0]), int(self._t[i1 - 1]))
            if span != self._fitted:
                self._fitted = span
                self._est = self._fit(*(self._cols[k][i0:i1] for k in ("x", "y", "vx", "vy")))
            if self._est is not None:
                rows.append((T, *self._est))
        out = FOE.array(t=np.array([r[0] for r in rows], np.int64),
                        x=np.array([r[1] for r in rows]), y=np.array([r[2] for r in rows]),
                        support=np.array([r[3] for r in rows], np.float64),
                        total=np.array([r[4] for r in rows], np.float64))
        return packet.with_series(FOE.name, out)

    def _fit(self, x, y, vx, vy):
        """(x, y, inliers, n) of the FOE fitted to these flow events, or None."""
        p = self.params
        s = np.hypot(vx, vy)
        ux, uy = vx / s, vy / s
        mx, my = -uy, ux                  # unit normal of each flow line
        c = mx * x + my * y               # the line: m . q = c
        n = len(x)
        sin_tol = math.sin(math.radians(p.tolerance_deg))
        rng = self._rng
        sample = (rng.choice(n, p.ransac_sample, replace=False) if n > p.ransac_sample
                  else np.arange(n))
        ij = rng.integers(0, n, (p.ransac_hypotheses, 2))
        a, b = ij[:, 0], ij[:, 1]
        det = mx[a] * my[b] - my[a] * mx[b]
        ok = np.abs(det) > 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            qx = (c[a] * my[b] - my[a] * c[b]) / det
            qy = (mx[a] * c[b] - c[a] * mx[b]) / det
        cand = np.stack([qx[ok], qy[ok]], 1)
        if self._last is not None:
            cand = np.vstack([np.array([self._last]), cand])
        if not len(cand):
            return None
        sx, sy, sux, suy = x[sample], y[sample], ux[sample], uy[sample]
        dx = sx[None, :] - cand[:, 0:1]
        dy = sy[None, :] - cand[:, 1:2]
        d = np.hypot(dx, dy)
        along = dx * sux[None, :] + dy * suy[None, :]
        across = np.abs(dx * suy[None, :] - dy * sux[None, :])
        inl = (along > 0) & (across < sin_tol * d) & (d > p.min_distance_px)
        q = cand[int(np.argmax(inl.sum(1)))].astype(np.float64)
        for _ in range(p.max_iter):
            dx, dy = x - q[0], y - q[1]
            d = np.hypot(dx, dy)
            sin_r = (dx * uy - dy * ux) / np.maximum(d, 1e-9)
            e = sin_r / sin_tol
            w = np.where((dx * ux + dy * uy > 0) & (d > p.min_distance_px) & (np.abs(e) < 1),
                         (1 - e * e) ** 2 / np.maximum(d, 1e-9) ** 2, 0.0)
            if np.count_nonzero(w) < p.min_inliers:
                self._last = None
                return None
            A = np.array([[np.sum(w * mx * mx), np.sum(w * mx * my)],
                          [np.sum(w * mx * my), np.sum(w * my * my)]])
            rhs = np.array([np.sum(w * mx * c), np.sum(w * my * c)])
            if abs(np.linalg.det(A)) < 1e-12 * max(np.trace(A) ** 2, 1e-300):
                self._last = None
                return None
            q_new = np.linalg.solve(A, rhs)
            done = np.hypot(*(q_new - q)) < 1e-3
            q = q_new
            if done:
                break
        dx, dy = x - q[0], y - q[1]
        d = np.hypot(dx, dy)
        inliers = int(np.count_nonzero((dx * ux + dy * uy > 0) & (d > p.min_distance_px)
                                       & (np.abs(dx * uy - dy * ux) < sin_tol * d)))
        if inliers < p.min_inliers or not np.all(np.isfinite(q)):
            self._last = None
            return None
        self._last = (float(q[0]), float(q[1]))
        return float(q[0]), float(q[1]), inliers, n
