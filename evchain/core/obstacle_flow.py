"""Flow on the obstacle before contact: from how far out the flow stage sees it, and how well.

:class:`ObstacleFlow` counts, per time bin, the flow events that land on the obstacle (the
truth's ``object_id`` at the event's pixel is one of its ``obstacle_ids``) while the true TTC
lies in (0, ``window_s``], with their normal-flow errors. A bin is *covered* when it holds at
least one such event. Its metrics (keys of ``metrics.flow``):

* ``obstacle_flow_since_s``: the true TTC at the start of the last unbroken run of covered
  bins, the one that reaches the window's end: from how many seconds before contact on the
  obstacle never goes a bin without flow (0 when the last bin is empty);
* ``obstacle_flow_coverage``: share of the window's bins that are covered;
* ``obstacle_n_flow``, ``obstacle_ree_normal_pct``, ``obstacle_outliers_ree_normal50``: count
  and normal-flow errors (mean relative error in %, share off by more than 50 %) of those
  events;
* ``obstacle_far_ree_normal_pct``: the mean relative normal-flow error in the window's first
  second (true TTC from ``window_s`` - 1 to ``window_s``), where the obstacle is far and its
  edges near the FOE are slow;
* ``obstacle_by_ttc``: count, coverage and errors per second of true TTC (3-2 s, 2-1 s, 1-0 s
  for a 3 s window);
* ``obstacle_window_s``: the longest true TTC of a bin in the window (shorter than
  ``window_s`` when the stream starts later); ``why_none`` says why a key is None.

Without an obstacle, or with a truth that knows no objects or no TTC, it gives no keys.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from evchain.core.truth import ObjectTruth, TtcTruth

#: a normal-flow error above this relative value is an outlier (as the flow scorer's)
OUTLIER_REL = 0.5


class ObstacleFlow:
    """Accumulates flow events on the obstacle per ``bin_us`` within the last ``window_s`` of
    true TTC; :meth:`add` per packet, :meth:`metrics` at the end."""

    def __init__(self, truth: object, window_s: float, bin_us: int) -> None:
        ids = getattr(truth, "obstacle_ids", None)
        self.enabled = (isinstance(truth, ObjectTruth) and isinstance(truth, TtcTruth)
                        and ids is not None and len(ids) > 0)
        self.truth = truth
        self.window_s = float(window_s)
        self.bin_us = int(bin_us)
        #: per bin: events on the obstacle, sum and count of finite rel. errors, outliers
        self.bins: dict[int, np.ndarray] = {}

    def _tau(self, t_us: np.ndarray) -> np.ndarray:
        tau = np.asarray(self.truth.ttc(np.asarray(t_us, np.float64)), np.float64)
        return np.broadcast_to(tau, np.shape(t_us))

    def add(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, ree_normal: np.ndarray) -> None:
        """Count the flow events (pixel x, y; time t in µs; their relative normal-flow errors)
        that are on the obstacle within the window."""
        if not self.enabled or len(t) == 0:
            return
        tau = self._tau(t)
        with np.errstate(invalid="ignore"):
            sel = np.flatnonzero((tau > 0) & (tau <= self.window_s))
        if not len(sel):
            return
        xs = np.asarray(x, np.float64)[sel]
        ys = np.asarray(y, np.float64)[sel]
        ts = np.asarray(t, np.float64)[sel]
        on = np.isin(np.asarray(self.truth.object_id(xs, ys, ts)), self.truth.obstacle_ids)
        if not on.any():
            return
        k = (np.asarray(t)[sel][on] // self.bin_us).astype(np.int64)
        err = np.asarray(ree_normal, np.float64)[sel][on]
        fin = np.isfinite(err)
        first = int(k.min())
        idx = k - first
        size = int(idx.max()) + 1
        cols = np.stack([np.bincount(idx, minlength=size).astype(np.float64),
                         np.bincount(idx, np.where(fin, err, 0.0), minlength=size),
                         np.bincount(idx, fin.astype(np.float64), minlength=size),
                         np.bincount(idx, (fin & (err > OUTLIER_REL)).astype(np.float64),
                                     minlength=size)], axis=1)
        for i in np.flatnonzero(cols[:, 0]):
            key = first + int(i)
            prev = self.bins.get(key)
            self.bins[key] = cols[i] if prev is None else prev + cols[i]

    def metrics(self, t_start_us: int, t_end_us: int) -> dict[str, Any]:
        """The metrics over the bins of [t_start_us, t_end_us) whose true TTC at the bin's
        centre lies in (0, window_s]."""
        if not self.enabled:
            return {}
        if t_end_us <= t_start_us:
            return {"obstacle_flow_since_s": None,
                    "why_none": {"obstacle_flow_since_s": "the stream spans no time"}}
        ks = np.arange(t_start_us // self.bin_us, (t_end_us - 1) // self.bin_us + 1)
        with np.errstate(invalid="ignore"):
            tau_mid = self._tau((ks + 0.5) * self.bin_us)
            win = (tau_mid > 0) & (tau_mid <= self.window_s)
        if not win.any():
            return {"obstacle_flow_since_s": None, "obstacle_window_s": 0.0,
                    "why_none": {"obstacle_flow_since_s": f"the true TTC is never within "
                                 f"{self.window_s:g} s in the stream"}}
        ks, tau_mid = ks[win], tau_mid[win]
        rows = np.array([self.bins.get(int(k), np.zeros(4)) for k in ks])
        covered = rows[:, 0] > 0
        run = len(covered)
        while run and covered[run - 1]:
            run -= 1
        since = 0.0 if run == len(covered) else float(self._tau(np.array([ks[run]])
                                                               * float(self.bin_us))[0])
        tau_start = self._tau(ks * float(self.bin_us))
        out: dict[str, Any] = {
            "obstacle_window_s": min(float(np.nanmax(tau_start)), self.window_s),
            "obstacle_flow_since_s": min(since, self.window_s),
            "obstacle_flow_coverage": float(covered.mean()),
            **_errors(rows),
            "obstacle_far_ree_normal_pct": _errors(rows[tau_mid > self.window_s - 1])[
                "obstacle_ree_normal_pct"],
            "obstacle_by_ttc": [],
        }
        for hi in range(math.ceil(self.window_s), 0, -1):
            band = (tau_mid <= min(hi, self.window_s)) & (tau_mid > hi - 1)
            if band.any():
                out["obstacle_by_ttc"].append({
                    "ttc_s": [hi - 1, min(hi, self.window_s)],
                    "coverage": float(covered[band].mean()), **_errors(rows[band])})
        far = f"{max(self.window_s - 1, 0):g}-{self.window_s:g} s"
        reasons = {"obstacle_ree_normal_pct": "no flow event on the obstacle in the window",
                   "obstacle_outliers_ree_normal50": "no flow event on the obstacle in the window",
                   "obstacle_far_ree_normal_pct": f"no flow event on the obstacle at a true TTC "
                                                  f"of {far} (or the stream starts closer)"}
        why = {k: r for k, r in reasons.items() if out[k] is None}
        if why:
            out["why_none"] = why
        return out


def _errors(rows: np.ndarray) -> dict[str, Any]:
    n, s, n_fin, n_out = rows.sum(axis=0) if len(rows) else np.zeros(4)
    return {"obstacle_n_flow": int(n),
            "obstacle_ree_normal_pct": 100.0 * s / n_fin if n_fin else None,
            "obstacle_outliers_ree_normal50": n_out / n_fin if n_fin else None}
