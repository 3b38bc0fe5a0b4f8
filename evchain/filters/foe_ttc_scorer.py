"""``foe_ttc_scorer``: FOE and TTC errors against the ground truth, metrics and pictures."""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from evchain.core.camera_scale import derived
from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import FlowPacket
from evchain.core.series import FOE, FOE_ERROR, ROTATION_FIELDS, TTC, TTC_CLUSTERS, TTC_ERROR
from evchain.core.truth import FoeTruth, ObjectTruth, RotationTruth, TtcTruth, not_scored

#: bins of the true TTC (s) for ``bias_on_obstacle_by_ttc``
TTC_BINS_S = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 3.0))


def _truth_foe(truth: FoeTruth, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(t) == 0:
        return np.full(len(t), np.nan), np.full(len(t), np.nan)
    x, y = truth.foe(t.astype(np.float64))
    return (np.broadcast_to(np.asarray(x, np.float64), t.shape).copy(),
            np.broadcast_to(np.asarray(y, np.float64), t.shape).copy())


def _truth_rotation_deg_s(truth, t: np.ndarray) -> np.ndarray:
    """The true angular velocity at times ``t`` as ``[len(t), 3]`` deg/s (NaN when the truth
    has no :class:`~evchain.core.truth.RotationTruth`)."""
    if not isinstance(truth, RotationTruth) or len(t) == 0:
        return np.full((len(t), 3), np.nan)
    w = truth.angular_velocity(t.astype(np.float64))
    return np.degrees(np.stack([np.broadcast_to(np.asarray(c, np.float64), t.shape)
                                for c in w], axis=1))


def _truth_ttc(truth: TtcTruth, t: np.ndarray) -> np.ndarray:
    if len(t) == 0:
        return np.full(len(t), np.nan)
    tau = truth.ttc(t.astype(np.float64))
    return np.broadcast_to(np.asarray(tau, np.float64), t.shape).copy()


def on_obstacle(truth, x, y, t_us, radius_px: int) -> np.ndarray | None:
    """Whether the obstacle is seen at (x, y) or at any position offset by whole pixels of at
    most ``radius_px`` in x and y (a (2 r + 1)^2 grid) at t_us, per element (1-D arrays); one
    ``object_id`` call for all of them. None when the truth knows no objects (not an
    :class:`~evchain.core.truth.ObjectTruth`) or no obstacle (no or empty ``obstacle_ids``).
    Non-finite positions: False."""
    if not isinstance(truth, ObjectTruth):
        return None
    ids = truth.obstacle_ids
    if ids is None or len(ids) == 0:
        return None
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    t = np.asarray(t_us, np.float64)
    finite = np.isfinite(x) & np.isfinite(y)
    if not len(x):
        return np.zeros(0, bool)
    off = np.arange(-radius_px, radius_px + 1, dtype=np.float64)
    ox, oy = (a.ravel() for a in np.meshgrid(off, off))
    qx = np.where(finite, x, 0.0)[:, None] + ox[None, :]
    qy = np.where(finite, y, 0.0)[:, None] + oy[None, :]
    qt = np.broadcast_to(t[:, None], qx.shape)
    seen = np.asarray(truth.object_id(qx, qy, qt)).reshape(qx.shape)
    return np.isin(seen, ids).any(axis=1) & finite


def foe_angle_deg(x, y, xt, yt, f: float | None, cx: float, cy: float) -> np.ndarray:
    """Angle between the viewing rays through the estimated and the true FOE, in degrees."""
    if f is None:
        return np.full(np.shape(x), np.nan)
    a = np.stack([np.asarray(x) - cx, np.asarray(y) - cy, np.full(np.shape(x), f)], -1)
    b = np.stack([np.asarray(xt) - cx, np.asarray(yt) - cy, np.full(np.shape(x), f)], -1)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.degrees(np.arctan2(cross, dot))


#: the FOE metrics that are None when nothing is scored
FOE_KEYS = ("dx_mean_px", "dx_std_px", "dy_mean_px", "dy_std_px", "angle_mean_deg",
            "angle_std_deg")


def _median_or_none(rel: np.ndarray) -> float | None:
    """The median of relative errors (misses are infinite); None when that is infinite
    (more than half of them misses) or there are none."""
    if not len(rel):
        return None
    m = float(np.median(rel))
    return m if math.isfinite(m) else None


#: the FOE's lag is searched up to this far (ms)
LAG_MAX_MS = 500.0
#: ... and defined only where the true FOE coordinate varies by at least this (std, px)
LAG_MIN_STD_PX = 1.0


def foe_lag_ms(t_us: np.ndarray, est: np.ndarray, true: np.ndarray,
               max_lag_ms: float = LAG_MAX_MS, min_std_px: float = LAG_MIN_STD_PX
               ) -> float | None:
    """How late an estimated FOE coordinate follows the true one: the lag (ms, positive =
    the estimate is late) that maximises the correlation of ``est(t)`` with ``true(t - lag)``.

    Both are resampled on a uniform grid (the median spacing of ``t_us``); lags are searched
    in whole grid steps up to ``max_lag_ms`` either way and refined by a parabola through the
    best three. None where the truth varies too little to tell (std below ``min_std_px``), or
    with too few finite samples.
    """
    ok = np.isfinite(est) & np.isfinite(true)
    t, est, true = t_us[ok].astype(np.float64), est[ok], true[ok]
    if len(t) < 8 or np.std(true) < min_std_px:
        return None
    step = float(np.median(np.diff(t)))
    if step <= 0:
        return None
    grid = np.arange(t[0], t[-1] + step / 2, step)
    a = np.interp(grid, t, est)
    b = np.interp(grid, t, true)
    k_max = min(int(max_lag_ms * 1000.0 / step), len(grid) // 2)
    lags = np.arange(-k_max, k_max + 1)
    corr = np.full(len(lags), -np.inf)
    for i, k in enumerate(lags):
        x, y = (a[k:], b[:len(b) - k]) if k >= 0 else (a[:k], b[-k:])
        if len(x) > 2 and np.std(x) > 0 and np.std(y) > 0:
            corr[i] = float(np.corrcoef(x, y)[0, 1])
    i = int(np.argmax(corr))
    if not np.isfinite(corr[i]):
        return None
    shift = 0.0
    if 0 < i < len(lags) - 1 and np.all(np.isfinite(corr[i - 1:i + 2])):
        c0, c1, c2 = corr[i - 1:i + 2]
        den = c0 - 2 * c1 + c2
        shift = 0.5 * (c0 - c2) / den if den < 0 else 0.0
    return float((lags[i] + shift) * step / 1000.0)


def foe_lag_metrics(foe: np.ndarray) -> dict:
    """``lag_ms`` of the FOE coordinate whose truth varies more (``lag_axis`` x or y) over the
    ``foe_error`` entries given; None each where the truth is about constant."""
    if not len(foe):
        return {"lag_ms": None, "lag_axis": None}
    sx, sy = (float(np.nanstd(foe[c])) if np.isfinite(foe[c]).any() else 0.0
              for c in ("x_true", "y_true"))
    axis = "y" if sy >= sx else "x"
    lag = foe_lag_ms(foe["t"], foe[axis], foe[f"{axis}_true"])
    return {"lag_ms": lag, "lag_axis": axis if lag is not None else None}


class FoeTtcScorer(Filter):
    """Scores FOE (|dx|, |dy|, ray angle) and TTC (relative error) against the ground truth.

    Pass-through. Appends series ``foe_error`` (per ``foe`` entry) and ``ttc_error`` (per ``ttc``
    entry: the cluster's centre x, y and ``on_obstacle``: 1 if it lies on the obstacle at that
    tick, 0 if not, -1 if the truth cannot tell; ``tau_true_s`` and ``rel_error`` -1 where the
    truth has no TTC). At the end writes ``metrics.foe`` (``dx_mean_px``,
    ``dx_std_px``, ``dy_mean_px``, ``dy_std_px``, ``angle_mean_deg`` after ``warmup_s``;
    thesis eq. 4.1; ``lag_ms``: how late the estimate follows the true FOE where that moves,
    :func:`foe_lag_ms`; ``window_s``: the seconds after the warm-up that were scored;
    ``rotation_rate_error_deg_s``: the median norm of the difference between the estimated and
    the true angular velocity, where the ``foe`` entries carry one and the truth knows it,
    :meth:`_rotation_metrics`) and ``metrics.ttc`` over the last ``last_window_s`` before
    collision, sampled every ``sample_every_us`` (a time without an estimate of at most
    ``max_age_us`` counts as a miss; ``window_s`` and ``window_span_s``: the window actually
    scored, which is shorter than asked when the stream has a true TTC for less time, and then
    a warning in ``report.json`` says so; so does a stream no longer than the FOE warm-up):

    * ``share_on_obstacle_within_20pct`` (the headline): share of the times at which the
      reported cluster lies on the obstacle (the truth's ``object_id`` sees one of its
      ``obstacle_ids`` at the cluster centre or within ``obstacle_margin_px`` of it) and its tau
      is within 20 % of the true TTC; ``coverage_on_obstacle``: share on the obstacle, whatever
      its tau; ``median_rel_error_on_obstacle``: median relative error at the times on the
      obstacle (None if never); ``misses``: the shares of the window's times lost, by reason
      (no estimate; the reported cluster off the obstacle, and of those the times at which a
      live cluster of ``ttc_clusters`` lay on it, None without that series; on the obstacle
      but more than 20 % off: these three and the headline sum to 1);
      ``bias_on_obstacle_by_ttc``: the median signed relative error (estimate - true) / true at
      the times on the obstacle, by the true TTC's bin (keys 0-500ms, 500-1000ms,
      1000-2000ms, 2000-3000ms; None in a bin without such times): whether the reported TTC
      runs long or short as the obstacle nears. All five are None when the truth knows no
      objects (no ``object_id``, e.g. the synthetic expansion or recorded
      data: then ``not_scored`` names them) or no obstacle.
    * ``median_rel_error_last3s``, ``share_within_10pct``, ``share_within_20pct``,
      ``coverage_last3s``: whatever cluster is reported, so a roadside object whose TTC happens
      to match the car's counts as a hit.

    A metric that cannot be given is None, and ``why_none`` says why: no FOE after the
    warm-up (a string), a median over a window more than half of which has no estimate (a miss
    is an infinite error), no estimate on the obstacle, no obstacle in the scene at all (no
    true TTC: nothing is scored, ``n_estimates`` still counts the TTCs reported).

    A stage with an ``id`` writes ``metrics.foe@ID`` and ``metrics.ttc@ID``. With ``plots``,
    PNGs: FOE error over time, TTC against truth (estimates on and off the obstacle in their own
    colours), and frame snapshots with flow, FOE and clusters.
    """

    name = "foe_ttc_scorer"
    scorer = True
    consumes = FlowPacket
    produces = None
    optional_series = (FOE, TTC, TTC_CLUSTERS)
    adds_series = (FOE_ERROR, TTC_ERROR)
    needs_truth = (FoeTruth, TtcTruth)
    uses_truth = (ObjectTruth, RotationTruth)
    output_paths = ("plot_dir",)

    class Params(FilterParams):
        warmup_s: float = Field(1.0, ge=0, description="FOE errors before this (from the "
                                "stream start) are not scored")
        last_window_s: float = Field(3.0, gt=0, description="TTC window before collision")
        sample_every_us: int = Field(10_000, ge=1, description="TTC scoring grid")
        max_age_us: int = Field(50_000, ge=0, description="an estimate older than this at a "
                                "grid time counts as missing")
        obstacle_margin_px: int | None = Field(
            None, ge=0, le=40, description="the reported cluster lies on the obstacle when the "
            "obstacle is seen at its centre or at any pixel up to this far from it in x and y: "
            "a cluster of edge events sits on the car's outline, so its centre can fall just "
            "beside the car; null: 2 px x f / 380.6 px, rounded (it belongs to ttc's "
            "clusters, whose sizes follow the camera)")
        plots: bool = Field(True, description="write the PNGs (needs ground truth)")
        plot_dir: str = Field("plots", description="folder for the PNGs, in the output folder")
        snapshot_ttc_s: list[float] = Field(
            default_factory=lambda: [1.0, 0.3],
            description="frame snapshots when the true TTC falls below these (and at the end)")
        snapshot_window_us: int = Field(20_000, ge=1, description="flow events of this last "
                                        "stretch of time go into a snapshot")

    def reset(self) -> None:
        self._t0: int | None = None
        self._t_end: int | None = None
        self._geometry = None
        self._foe: list[np.ndarray] = []
        self._ttc: list[np.ndarray] = []
        self._recent: list[tuple] = []
        self._last_foe = (math.nan, math.nan)
        self._last_clusters: np.ndarray | None = None
        self._clusters: list[np.ndarray] = []
        self._snapshots: list[dict] = []
        self._taken: set[float] = set()

    def _margin(self) -> int:
        """``obstacle_margin_px`` on this camera (derived when null)."""
        return round(derived(self.params.obstacle_margin_px, 2.0, self._geometry))

    def process(self, packet: FlowPacket) -> FlowPacket:
        truth = self.truth
        if self._t0 is None:
            self._t0 = packet.t_start
            self._geometry = packet.geometry
        self._t_end = packet.t_end
        g = packet.geometry
        out = packet
        foe = packet.series.get(FOE.name)
        if foe is not None and len(foe):
            t = np.asarray(foe["t"], np.int64)
            xt, yt = _truth_foe(truth, t)
            x, y = np.asarray(foe["x"], np.float64), np.asarray(foe["y"], np.float64)
            err = FOE_ERROR.array(t=t, x=x, y=y, x_true=xt, y_true=yt, dx=x - xt, dy=y - yt,
                                  angle_deg=foe_angle_deg(x, y, xt, yt, g.f, g.cx, g.cy))
            w = np.stack([np.asarray(foe[c], np.float64) for c in ROTATION_FIELDS], 1)
            wt = _truth_rotation_deg_s(truth, t)
            known = np.isfinite(wt).all(axis=1)
            wt[~known] = 0.0
            for i, c in enumerate(ROTATION_FIELDS):
                err[c] = w[:, i]
                err[c.replace("_deg", "_true_deg")] = wt[:, i]
            err["rotation_error_deg_s"] = np.where((foe["rotation"] > 0) & known,
                                                   np.linalg.norm(w - wt, axis=1), -1.0)
            self._foe.append(err)
            self._last_foe = (float(x[-1]), float(y[-1]))
            out = out.with_series(FOE_ERROR.name, err)
        ttc = packet.series.get(TTC.name)
        if ttc is not None and len(ttc):
            t = np.asarray(ttc["t"], np.int64)
            tt = _truth_ttc(truth, t)
            tau = np.asarray(ttc["tau_s"], np.float64)
            defined = np.isfinite(tt) & (tt > 0)  # else -1: nothing ahead to contact
            with np.errstate(invalid="ignore", divide="ignore"):
                rel = np.where(defined, np.abs(tau - tt) / tt, -1.0)
            tt = np.where(defined, tt, -1.0)
            on = on_obstacle(truth, ttc["x"], ttc["y"], t, self._margin())
            err = TTC_ERROR.array(t=t, tau_s=tau, tau_true_s=tt, rel_error=rel,
                                  cluster=ttc["cluster"], x=ttc["x"], y=ttc["y"],
                                  on_obstacle=np.full(len(t), -1) if on is None else on)
            self._ttc.append(err)
            out = out.with_series(TTC_ERROR.name, err)
        cl = packet.series.get(TTC_CLUSTERS.name)
        if cl is not None and len(cl):
            self._last_clusters = cl[cl["t"] == cl["t"][-1]].copy()
            self._clusters.append(cl[["t", "x", "y"]].copy())
        if self.params.plots:
            self._keep_recent(packet)
            self._maybe_snapshot(packet)
        return out

    # -- snapshots -------------------------------------------------------------------------
    def _keep_recent(self, packet: FlowPacket) -> None:
        if len(packet):
            self._recent.append((packet.x.copy(), packet.y.copy(), packet.t.copy(),
                                 packet.vx.copy(), packet.vy.copy()))
        cut = packet.t_end - self.params.snapshot_window_us
        while self._recent and self._recent[0][2][-1] < cut:
            self._recent.pop(0)

    def _snapshot(self, t_us: int, label: str) -> dict:
        cut = t_us - self.params.snapshot_window_us
        if self._recent:
            x, y, t, vx, vy = (np.concatenate(c) for c in zip(*self._recent, strict=True))
            k = t >= cut
            x, y, vx, vy = x[k], y[k], vx[k], vy[k]
        else:
            x = y = vx = vy = np.zeros(0)
        xt, yt = _truth_foe(self.truth, np.array([t_us], np.int64))
        return {"t_us": t_us, "label": label, "x": x, "y": y, "vx": vx, "vy": vy,
                "foe_est": self._last_foe, "foe_true": (float(xt[0]), float(yt[0])),
                "clusters": self._last_clusters,
                "tau_true": float(_truth_ttc(self.truth, np.array([t_us]))[0])}

    def _maybe_snapshot(self, packet: FlowPacket) -> None:
        tau = float(_truth_ttc(self.truth, np.array([packet.t_end], np.int64))[0])
        if not np.isfinite(tau):
            return
        for level in self.params.snapshot_ttc_s:
            if level not in self._taken and tau <= level:
                self._taken.add(level)
                self._snapshots.append(self._snapshot(packet.t_end, f"ttc{level:g}s"))

    # -- metrics ---------------------------------------------------------------------------
    def _foe_metrics(self, foe: np.ndarray) -> dict:
        p = self.params
        start = self._t0 + int(round(p.warmup_s * 1e6))
        window_s = max(0.0, (self._t_end - start) * 1e-6)
        base = {"warmup_s": p.warmup_s, "window_s": window_s}
        after = foe["t"] >= start
        # the rotation is scored wherever the truth knows it, also where the FOE is undefined
        # (a camera turning in place, a recording whose truth is the gyro's)
        rotation, why_rotation = self._rotation_metrics(foe[after])
        k = after & np.isfinite(foe["dx"]) & np.isfinite(foe["dy"])
        if not k.any():
            stream_s = (self._t_end - self._t0) * 1e-6
            if window_s == 0.0:
                why = (f"the stream ({stream_s:g} s) is not longer than the FOE warm-up "
                       f"(warmup_s {p.warmup_s:g} s): nothing is scored")
                self.context.warn(f"{self.id}: {why}")
            elif len(foe) and not np.isfinite(foe["x_true"][foe["t"] >= start]).any():
                why = "the true FOE is undefined (no forward motion) after the warm-up"
            else:
                why = (f"no FOE estimate in the {window_s:g} s after the warm-up (the "
                       "estimators' own metrics say why)")
            return {**dict.fromkeys(FOE_KEYS), "n": 0, **base, "lag_ms": None,
                    "lag_axis": None, **rotation, "why_none": why}
        adx, ady = np.abs(foe["dx"][k]), np.abs(foe["dy"][k])
        ang = foe["angle_deg"][k]
        m = {"dx_mean_px": float(adx.mean()), "dx_std_px": float(adx.std()),
             "dy_mean_px": float(ady.mean()), "dy_std_px": float(ady.std()),
             "angle_mean_deg": float(np.nanmean(ang)) if np.isfinite(ang).any() else None,
             "angle_std_deg": float(np.nanstd(ang)) if np.isfinite(ang).any() else None,
             "n": int(k.sum()), **base, **foe_lag_metrics(foe[k]), **rotation}
        if why_rotation is not None:
            m["why_none"] = {key: why_rotation for key, v in rotation.items() if v is None}
        return m

    def _rotation_metrics(self, foe: np.ndarray) -> tuple[dict, str | None]:
        """The camera's rotation rate against the truth over the scored ``foe_error`` entries,
        and why they are None (else None): ``rotation_rate_error_deg_s``, the median of
        |w - w_true| (the norm of the difference of the angular velocity vectors, deg/s) over
        the entries that carry an estimate; ``rotation_rate_error_wx_deg_s`` (wy, wz): the
        median of each axis' |difference|; ``rotation_rate_true_deg_s``: the median |w_true|,
        the scale of what was estimated; ``rotation_coverage``: the share of entries with an
        estimate. None where nothing was estimated or the truth knows no rotation."""
        keys = ("rotation_rate_error_deg_s", *(f"rotation_rate_error_{c}" for c in
                                               ROTATION_FIELDS),
                "rotation_rate_true_deg_s")
        if not isinstance(self.truth, RotationTruth):
            why = not_scored(keys, self.truth, RotationTruth)
            return {**dict.fromkeys(keys), "rotation_coverage": None, "not_scored": why}, why
        have = foe["rotation_error_deg_s"] >= 0
        cover = float(have.mean()) if len(foe) else None
        if not have.any():
            return ({**dict.fromkeys(keys), "rotation_coverage": cover},
                    "no scored FOE estimate carries the camera's angular velocity (foe_map's "
                    "and foe_lines' never do, foe_fit's only with a focal length and where it "
                    "fitted)")
        true = np.stack([foe[c.replace("_deg", "_true_deg")][have] for c in ROTATION_FIELDS], 1)
        d = np.abs(np.stack([foe[c][have] for c in ROTATION_FIELDS], 1) - true)
        return {"rotation_rate_error_deg_s": float(np.median(foe["rotation_error_deg_s"][have])),
                **{f"rotation_rate_error_{c}": float(np.median(d[:, i]))
                   for i, c in enumerate(ROTATION_FIELDS)},
                "rotation_rate_true_deg_s": float(np.median(np.linalg.norm(true, axis=1))),
                "rotation_coverage": cover}, None

    def _ttc_metrics(self, ttc: np.ndarray) -> tuple[dict, dict]:
        p = self.params
        grid = np.arange(self._t0, self._t_end, p.sample_every_us, dtype=np.int64)
        truth = _truth_ttc(self.truth, grid)
        ok = np.isfinite(truth) & (truth > 0)
        if not ok.any():
            return {"n": 0, "n_estimates": int(len(ttc)), "window_s": 0.0,
                    "why_none": "no obstacle ahead: the true TTC is undefined at every time "
                                "of the stream, so no TTC is scored"}, {}
        idx = np.searchsorted(ttc["t"], grid, side="right") - 1
        have = (idx >= 0)
        idx = np.maximum(idx, 0)
        if len(ttc):
            have &= (grid - ttc["t"][idx]) <= p.max_age_us
            est = np.where(have, ttc["tau_s"][idx], np.nan)
        else:
            have[:] = False
            est = np.full(len(grid), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.where(have & ok, np.abs(est - truth) / truth, np.inf)
        t_last = grid[ok][-1]
        win = ok & (grid >= t_last - int(p.last_window_s * 1e6))
        relw = rel[win]
        t_first = int(grid[win][0])
        window_s = (t_last - t_first) * 1e-6
        with np.errstate(invalid="ignore", divide="ignore"):
            signed = (est[win] - truth[win]) / truth[win]
        m = {**self._obstacle_metrics(ttc, grid[win], idx[win], have[win], relw, signed,
                                      truth[win]),
             "median_rel_error_last3s": _median_or_none(relw),
             "share_within_10pct": float(np.mean(relw <= 0.10)),
             "share_within_20pct": float(np.mean(relw <= 0.20)),
             "coverage_last3s": float(np.mean(np.isfinite(relw))),
             "median_rel_error_all": _median_or_none(rel[ok]),
             "share_within_20pct_all": float(np.mean(rel[ok] <= 0.20)),
             "window_s": window_s,
             "window_span_s": [t_first * 1e-6, t_last * 1e-6],
             "n_estimates": int(len(ttc))}
        if t_first - (t_last - int(p.last_window_s * 1e6)) > p.sample_every_us:  # a grid step
            self.context.warn(
                f"{self.id}: the TTC window is {window_s:g} s, shorter than last_window_s "
                f"{p.last_window_s:g} s (the stream has a true TTC only from {t_first * 1e-6:g} "
                f"s, its last at {t_last * 1e-6:g} s); the TTC metrics cover those "
                f"{window_s:g} s")
        why = {}
        for key, values in (("median_rel_error_last3s", relw), ("median_rel_error_all", rel[ok])):
            if m[key] is None:
                why[key] = (f"estimates at {np.mean(np.isfinite(values)):.0%} of the times; a "
                            "time without one counts as an infinite error, so the median is "
                            "undefined below 50%")
        if m.get("median_rel_error_on_obstacle", 0) is None and "not_scored" not in m \
                and m.get("coverage_on_obstacle") is not None:
            why["median_rel_error_on_obstacle"] = "no estimate on the obstacle in the window"
        if why:
            m["why_none"] = why
        curves = {"grid_s": grid * 1e-6, "truth": truth}
        return m, curves

    def _obstacle_metrics(self, ttc: np.ndarray, grid: np.ndarray, idx: np.ndarray,
                          have: np.ndarray, rel: np.ndarray, signed: np.ndarray,
                          truth: np.ndarray) -> dict:
        """The on-obstacle metrics over the window's grid times (estimate index idx where have,
        relative errors rel, signed relative errors signed, true TTCs truth); None each when
        the truth cannot tell."""
        on = np.zeros(len(grid), bool)
        sub = on_obstacle(self.truth, ttc["x"][idx[have]], ttc["y"][idx[have]],
                          grid[have], self._margin())
        if sub is None:
            keys = ("share_on_obstacle_within_20pct", "coverage_on_obstacle",
                    "median_rel_error_on_obstacle", "misses", "bias_on_obstacle_by_ttc")
            if not isinstance(self.truth, ObjectTruth):
                return {**dict.fromkeys(keys),
                        "not_scored": not_scored(keys, self.truth, ObjectTruth)}
            return dict.fromkeys(keys)
        on[have] = sub
        hit = on & (rel <= 0.20)
        off = have & ~on
        there = self._obstacle_cluster_at(grid)
        n = max(len(grid), 1)
        misses = {"no_estimate": float(np.sum(~have) / n),
                  "off_obstacle": float(np.sum(off) / n),
                  "off_obstacle_with_a_cluster_on_it": (None if there is None else
                                                        float(np.sum(off & there) / n)),
                  "on_obstacle_over_20pct": float(np.sum(on & ~hit) / n)}
        bias = {}
        for lo, hi in TTC_BINS_S:
            sel = on & (truth >= lo) & (truth < hi)
            key = f"{lo * 1000:g}-{hi * 1000:g}ms"
            bias[key] = float(np.median(signed[sel])) if sel.any() else None
        return {"share_on_obstacle_within_20pct": float(np.mean(hit)),
                "coverage_on_obstacle": float(np.mean(on)),
                "median_rel_error_on_obstacle": float(np.median(rel[on])) if on.any() else None,
                "misses": misses, "bias_on_obstacle_by_ttc": bias}

    def _obstacle_cluster_at(self, grid: np.ndarray) -> np.ndarray | None:
        """Per grid time: whether any live cluster of the latest ``ttc_clusters`` tick at most
        ``max_age_us`` before it lies on the obstacle (None without that series)."""
        if not self._clusters:
            return None
        cl = np.concatenate(self._clusters)
        ticks = np.unique(cl["t"])
        j = np.searchsorted(ticks, grid, side="right") - 1
        ok = (j >= 0) & ((grid - ticks[np.maximum(j, 0)]) <= self.params.max_age_us)
        there = np.zeros(len(grid), bool)
        if not ok.any():
            return there
        rows = np.searchsorted(cl["t"], ticks[j[ok]], side="left")
        ends = np.searchsorted(cl["t"], ticks[j[ok]], side="right")
        counts = ends - rows
        which = np.repeat(np.nonzero(ok)[0], counts)
        pick = np.concatenate([np.arange(a, b) for a, b in zip(rows, ends, strict=True)]) \
            if len(rows) else np.zeros(0, np.int64)
        on = on_obstacle(self.truth, cl["x"][pick], cl["y"][pick], grid[which],
                         self._margin())
        np.logical_or.at(there, which, on)
        return there

    def flush(self):
        if self._t0 is None:
            return None
        foe = np.concatenate(self._foe) if self._foe else np.zeros(0, FOE_ERROR.dtype)
        ttc = np.concatenate(self._ttc) if self._ttc else np.zeros(0, TTC_ERROR.dtype)
        fm = self._foe_metrics(foe)
        tm, curves = self._ttc_metrics(ttc)
        self.context.metrics[self.metrics_key("foe")] = fm
        self.context.metrics[self.metrics_key("ttc")] = tm
        if self.params.plots:
            self._plots(foe, ttc, curves)
        return None

    def _plots(self, foe: np.ndarray, ttc: np.ndarray, curves: dict) -> None:
        from evchain.report import foe_ttc_plots as plots

        d = self.context.output_path(self.params.plot_dir)
        g = self._geometry
        if len(foe):
            plots.plot_foe_error(foe["t"] * 1e-6, foe["dx"], foe["dy"], d / "foe_error.png",
                                 warmup_s=(self._t0 * 1e-6 + self.params.warmup_s))
        if curves:
            plots.plot_ttc(ttc["t"] * 1e-6, ttc["tau_s"], curves["grid_s"], curves["truth"],
                           d / "ttc.png", on_obstacle=ttc["on_obstacle"])
        snaps = list(self._snapshots)
        if self._recent or not snaps:
            snaps.append(self._snapshot(self._t_end, "end"))
        for s in snaps:
            title = f"t = {s['t_us'] * 1e-6:.3f} s"
            if np.isfinite(s["tau_true"]):
                title += f", true TTC {s['tau_true']:.2f} s"
            plots.plot_snapshot(g.width, g.height, s["x"], s["y"], s["vx"], s["vy"],
                                s["foe_est"], s["foe_true"], s["clusters"],
                                d / f"snapshot_{s['label']}.png", title)
