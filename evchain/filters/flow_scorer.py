"""Optical-flow scoring against ground truth: the ``flow_scorer`` stage and reusable helpers.

* :func:`flow_errors` gives per-event errors of flow events against a ground-truth provider
  (a :class:`~evchain.core.truth.FlowTruth`, also a ``FoeTruth`` for the invalid rate);
  :func:`summarize` turns them into metrics; :func:`score_flow` does both (pure numpy, for
  benchmarks).
* :class:`FlowScorer` (``flow_scorer``) passes flow packets through unchanged, appends the series
  ``flow_error`` per time bin and writes ``context.metrics["flow"]`` at the end of the stream,
  with the density from the flow filter's ``flow_density`` series
  (:class:`evchain.core.series.DensityCounter`; see ``docs/explanation/flow_scoring.md``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.obstacle_flow import ObstacleFlow
from evchain.core.packets import FlowPacket
from evchain.core.series import FLOW_DENSITY, FLOW_ERROR
from evchain.core.truth import FlowTruth, FoeTruth, ObjectTruth, TtcTruth, not_scored

#: outlier thresholds
OUTLIER_REL = 0.5  # relative endpoint error above 50 %
OUTLIER_DEG = 45.0  # angular error above 45 degrees
#: bins of the true normal speed |u_n| (px/s) for ``by_normal_speed``
NORMAL_SPEED_BINS = (0.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, math.inf)


def flow_errors(x, y, t, vx, vy, truth) -> dict[str, np.ndarray]:
    """Per-event errors of flow vectors (px/s) against ``truth`` (NaN where undefined).

    Keys: ``gt_ok`` (ground truth finite), ``ee`` |v - u| and ``ree`` |v - u| / |u| against the
    full ground truth u; ``ee_normal`` and ``ree_normal`` against u projected on the estimated
    normal v/|v|, whose length |u_n| is ``normal_speed``; ``ae_deg`` the 2-D angle between v and
    u; ``invalid`` (1.0/0.0, NaN without an FOE) whether v points more than 90 degrees away from
    p - foe (thesis Table 4.2).
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    t = np.asarray(t, np.float64)
    vx = np.asarray(vx, np.float64)
    vy = np.asarray(vy, np.float64)
    n = len(x)
    ux, uy = truth.flow(x, y, t)
    ux = np.broadcast_to(np.asarray(ux, np.float64), (n,))
    uy = np.broadcast_to(np.asarray(uy, np.float64), (n,))
    ok = np.isfinite(ux) & np.isfinite(uy)
    with np.errstate(invalid="ignore", divide="ignore"):
        speed = np.hypot(vx, vy)
        gt_speed = np.hypot(ux, uy)
        ee = np.where(ok, np.hypot(vx - ux, vy - uy), np.nan)
        ree = np.where(ok & (gt_speed > 0), ee / gt_speed, np.nan)
        nx = np.where(speed > 0, vx / speed, np.nan)
        ny = np.where(speed > 0, vy / speed, np.nan)
        un = ux * nx + uy * ny  # ground truth along the estimated normal
        ee_n = np.where(ok, np.hypot(vx - un * nx, vy - un * ny), np.nan)
        ree_n = np.where(ok & (np.abs(un) > 0), ee_n / np.abs(un), np.nan)
        ang = np.degrees(np.arctan2(np.abs(vx * uy - vy * ux), vx * ux + vy * uy))
        ae = np.where(ok & (gt_speed > 0) & (speed > 0), ang, np.nan)
    invalid = np.full(n, np.nan)
    if isinstance(truth, FoeTruth):
        fx, fy = truth.foe(t)
        fx = np.broadcast_to(np.asarray(fx, np.float64), (n,))
        fy = np.broadcast_to(np.asarray(fy, np.float64), (n,))
        dot = (x - fx) * vx + (y - fy) * vy
        defined = np.isfinite(dot) & ((x != fx) | (y != fy)) & (speed > 0)
        invalid = np.where(defined, (dot < 0).astype(np.float64), np.nan)
    return {"gt_ok": ok, "ee": ee, "ree": ree, "ee_normal": ee_n, "ree_normal": ree_n,
            "normal_speed": np.where(ok, np.abs(un), np.nan), "ae_deg": ae, "invalid": invalid}


SUM_KEYS = ("ee", "ree", "ee_normal", "ree_normal", "ae_deg", "invalid")


def partial_sums(errs: dict[str, np.ndarray]) -> dict[str, float]:
    """Sums and counts of the finite entries of each error. The flow scorer calls it once per
    time bin on the bin's events in stream order, so the sums do not depend on packet cuts."""
    out: dict[str, float] = {"n_flow": float(len(errs["ee"])),
                             "n_gt": float(np.count_nonzero(errs["gt_ok"]))}
    for k in SUM_KEYS:
        v = errs[k][np.isfinite(errs[k])]
        out[f"sum_{k}"] = float(v.sum())
        out[f"n_{k}"] = float(len(v))
    out["n_ree_out"] = float(np.count_nonzero(errs["ree"] > OUTLIER_REL))
    out["n_ree_normal_out"] = float(np.count_nonzero(errs["ree_normal"] > OUTLIER_REL))
    out["n_ae_out"] = float(np.count_nonzero(errs["ae_deg"] > OUTLIER_DEG))
    scored = np.isfinite(errs["ree_normal"])
    ree_n = errs["ree_normal"][scored]
    which = np.digitize(errs["normal_speed"][scored], NORMAL_SPEED_BINS[1:-1])
    for b in range(len(NORMAL_SPEED_BINS) - 1):
        r = ree_n[which == b]
        out[f"n_ree_normal_bin{b}"] = float(len(r))
        out[f"sum_ree_normal_bin{b}"] = float(r.sum())
        out[f"n_ree_normal_out_bin{b}"] = float(np.count_nonzero(r > OUTLIER_REL))
    return out


def merge_sums(parts: list[dict[str, float]]) -> dict[str, float]:
    keys = parts[0].keys() if parts else partial_sums(_empty_errs()).keys()
    return {k: math.fsum(p[k] for p in parts) for k in keys}


def _empty_errs() -> dict[str, np.ndarray]:
    e = np.zeros(0)
    return {"gt_ok": np.zeros(0, bool), "normal_speed": e, **{k: e for k in SUM_KEYS}}


def _mean(s: dict[str, float], key: str) -> float | None:
    n = s[f"n_{key}"]
    return s[f"sum_{key}"] / n if n else None


def _share(count: float, n: float) -> float | None:
    return count / n if n else None


def metrics_from_sums(s: dict[str, float]) -> dict[str, Any]:
    """Metrics (means and shares) from merged partial sums."""
    ree = _mean(s, "ree")
    ree_n = _mean(s, "ree_normal")
    return {
        "n_flow": int(s["n_flow"]),
        "n_scored": int(s["n_gt"]),
        "n_no_ground_truth": int(s["n_flow"] - s["n_gt"]),
        "aee_pxs": _mean(s, "ee"),
        "ree_pct": None if ree is None else 100.0 * ree,
        "aee_normal_pxs": _mean(s, "ee_normal"),
        "ree_normal_pct": None if ree_n is None else 100.0 * ree_n,
        "aae_deg": _mean(s, "ae_deg"),
        "invalid_rate": _mean(s, "invalid"),
        "outliers_ree50": _share(s["n_ree_out"], s["n_ree"]),
        "outliers_ree_normal50": _share(s["n_ree_normal_out"], s["n_ree_normal"]),
        "outliers_ae45": _share(s["n_ae_out"], s["n_ae_deg"]),
        "by_normal_speed": _by_normal_speed(s),
    }


def _by_normal_speed(s: dict[str, float]) -> list[dict[str, Any]]:
    """Per bin of the true normal speed |u_n| (:data:`NORMAL_SPEED_BINS`, px/s): the share of
    the events with a normal error, their mean normal relative error and outlier share, and
    what the bin adds to the run's mean and outlier share (its sum over all events)."""
    n_all = s["n_ree_normal"]
    out = []
    for b, (lo, hi) in enumerate(zip(NORMAL_SPEED_BINS[:-1], NORMAL_SPEED_BINS[1:],
                                     strict=True)):
        n, total = s[f"n_ree_normal_bin{b}"], s[f"sum_ree_normal_bin{b}"]
        n_out = s[f"n_ree_normal_out_bin{b}"]
        out.append({
            "normal_speed_pxs": [lo, None if math.isinf(hi) else hi],
            "share": _share(n, n_all),
            "ree_normal_pct": None if not n else 100.0 * total / n,
            "outliers_ree_normal50": _share(n_out, n),
            "adds_to_ree_normal_pct": None if not n_all else 100.0 * total / n_all,
            "adds_to_outliers_ree_normal50": _share(n_out, n_all),
        })
    return out


def summarize(errs: dict[str, np.ndarray]) -> dict[str, Any]:
    """Metrics of one set of per-event errors (see :func:`flow_errors`)."""
    return metrics_from_sums(partial_sums(errs))


def score_flow(x, y, t, vx, vy, truth) -> dict[str, Any]:
    """Score flow vectors against ``truth``: AEE (px/s), relative EE (%), both against the full
    and the normal-projected ground truth, AAE (deg), invalid rate (0-1, None without an FOE),
    outlier shares, counts. ``density`` is not known here (needs the input count)."""
    return summarize(flow_errors(x, y, t, vx, vy, truth))


class FlowScorer(Filter):
    """Scores flow events against ground truth (AEE, normal AEE, AAE, invalid rate, density).

    Ground truth: the source's (``context.truth``) or a DVSFLOW16 ``.mat`` file given as
    ``ground_truth``. Packets pass through unchanged, plus the series ``flow_error`` (one entry
    per ``bin_us`` with flow events: t = bin end, n, aee_pxs, aee_normal_pxs, aae_deg,
    invalid_rate). At the end ``metrics.flow`` (``metrics.flow@ID`` for a stage with an ``id``)
    holds the run's values; ``density`` = flow events / input events from the flow filter's
    ``flow_density`` series (None if it has none). The invalid rate needs the true FOE: without
    it, it is None and ``not_scored`` says why; without flow events to score the errors are
    None and ``why_none`` says so. ``by_normal_speed`` splits the normal relative error and
    its outliers by the true normal speed (:data:`NORMAL_SPEED_BINS`), with what each bin adds
    to the run's values.

    Flow on the obstacle before contact (a truth with object ids and a TTC, a scene with an
    obstacle): ``obstacle_flow_since_s``, from how many seconds of true TTC on every bin has
    flow events on the obstacle up to the end, ``obstacle_flow_coverage``, the share of such
    bins within the last ``obstacle_window_s``, and the normal-flow errors of those events
    (:mod:`evchain.core.obstacle_flow`).
    """

    name = "flow_scorer"
    scorer = True
    consumes = FlowPacket
    produces = None
    optional_series = (FLOW_DENSITY,)
    adds_series = (FLOW_ERROR,)
    needs_truth = (FlowTruth,)
    uses_truth = (FoeTruth, ObjectTruth, TtcTruth)
    truth_hint = "or give the parameter ground_truth: path/to/gt.mat (DVSFLOW16)"
    input_paths = ("ground_truth",)

    class Params(FilterParams):
        ground_truth: str | None = Field(
            None, description="DVSFLOW16 ground-truth .mat file; default: the source's truth")
        bin_us: int = Field(100_000, gt=0, description="time-series bin (us)")
        obstacle_window_s: float = Field(
            3.0, gt=0, description="flow on the obstacle is scored while its true TTC is at "
            "most this (s); a bin of bin_us with at least one flow event on it is covered")

    def truth_for(self, params, context):
        """The DVSFLOW16 file ``ground_truth`` if given, else the source's truth."""
        if params.ground_truth is None:
            return context.truth
        from evchain.io.dvsflow16 import DVSFLOW16Truth

        geom = context.geometry
        return DVSFLOW16Truth(Path(params.ground_truth),
                              height=None if geom is None else geom.height,
                              width=None if geom is None else geom.width)

    def reset(self) -> None:
        self.bins: dict[int, list[dict[str, np.ndarray]]] = {}
        self.bin_sums: list[dict[str, float]] = []
        self.n_in = 0
        self.n_out_reported = 0
        self.last = None
        self.t_start: int | None = None
        self.obstacle = ObstacleFlow(getattr(self, "truth", None), self.params.obstacle_window_s,
                                     self.params.bin_us)

    def _close_bins(self, keys: list[int]) -> np.ndarray:
        if not keys:
            return np.zeros(0, FLOW_ERROR.dtype)
        rows = []
        for k in keys:
            parts = self.bins.pop(k)
            errs = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
            s = partial_sums(errs)
            if s["n_flow"] == 0:
                continue
            self.bin_sums.append(s)
            m = metrics_from_sums(s)
            rows.append(((k + 1) * self.params.bin_us, m["n_flow"],
                         *(np.nan if m[key] is None else m[key]
                           for key in ("aee_pxs", "aee_normal_pxs", "aae_deg", "invalid_rate"))))
        names = FLOW_ERROR.dtype.names
        cols = list(zip(*rows, strict=True)) if rows else [[]] * len(names)
        return FLOW_ERROR.array(**{name: np.asarray(c)
                                   for name, c in zip(names, cols, strict=True)})

    def process(self, packet: FlowPacket) -> FlowPacket:
        dens = packet.series.get(FLOW_DENSITY.name)
        if dens is not None and len(dens):
            self.n_in += int(dens["n_in"].sum())
            self.n_out_reported += int(dens["n_out"].sum())
        if self.t_start is None:
            self.t_start = packet.t_start
        if len(packet):
            errs = flow_errors(packet.x, packet.y, packet.t, packet.vx, packet.vy, self.truth)
            self.obstacle.add(packet.x, packet.y, packet.t, errs["ree_normal"])
            k = packet.t // self.params.bin_us
            starts = np.flatnonzero(np.diff(k)) + 1  # times are sorted: bins are runs
            for a, b in zip([0, *starts.tolist()], [*starts.tolist(), len(k)], strict=True):
                self.bins.setdefault(int(k[a]), []).append({n: v[a:b] for n, v in errs.items()})
        done = sorted(kk for kk in self.bins if (kk + 1) * self.params.bin_us < packet.t_end) \
            if self.bins else []
        self.last = packet
        return packet.with_series(FLOW_ERROR.name, self._close_bins(done))

    def flush(self) -> FlowPacket | None:
        entries = self._close_bins(sorted(self.bins))
        merged = merge_sums(self.bin_sums)
        m = metrics_from_sums(merged)
        m["density"] = (self.n_out_reported / self.n_in) if self.n_in else None
        m["n_input_events"] = self.n_in if self.n_in else None
        if not isinstance(self.truth, FoeTruth):
            m["not_scored"] = not_scored(["invalid_rate"], self.truth, FoeTruth)
        if m["n_flow"] == 0:
            m["why_none"] = ("no flow events to score (no input events)" if not self.n_in
                             else "no flow events to score: the flow stage estimated none")
        elif m["n_scored"] == 0:
            m["why_none"] = "no flow event has ground truth"
        if self.last is not None:
            obstacle = self.obstacle.metrics(self.t_start, self.last.t_end)
            why = obstacle.pop("why_none", None)
            m.update(obstacle)
            if why and not isinstance(m.get("why_none"), str):
                m["why_none"] = {**m.get("why_none", {}), **why}
        self.context.metrics[self.metrics_key("flow")] = m
        if self.last is None:
            return None
        end = self.last.t_end
        return FlowPacket.empty(self.last.geometry, end, end).with_series(FLOW_ERROR.name,
                                                                          entries)
