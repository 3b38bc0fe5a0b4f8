"""The series that pass between stages: one definition (name and dtype) each.

A series is a numpy structured array with an int64 field ``t`` (µs) first, carried by packets
(see :mod:`evchain.core.packets`). Producers and readers both import the definitions from here;
filters declare which they need and add (``needs_series``, ``optional_series``, ``adds_series``
on :class:`~evchain.core.filter.Filter`), and pipeline validation checks that every stage's needs
are met upstream.

:class:`DensityCounter` is the flow filters' side of the density convention: every flow filter
appends :data:`FLOW_DENSITY` (input and flow events per fixed time bin) for the flow scorer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evchain.errors import ConfigError


@dataclass(frozen=True)
class SeriesDef:
    """A series' name, the dtype of its entries and a one-line description with units."""

    name: str
    dtype: np.dtype
    description: str = ""

    def __post_init__(self):
        dtype = np.dtype(self.dtype)
        if dtype.names is None or dtype.names[0] != "t" or dtype["t"] != np.int64:
            raise ValueError(f"series {self.name!r}: dtype must be structured with an int64 "
                             f"field 't' first, got {dtype}")
        object.__setattr__(self, "dtype", dtype)

    def array(self, **columns) -> np.ndarray:
        """Entries from equal-length columns (fields not given are 0)."""
        n = len(next(iter(columns.values()))) if columns else 0
        out = np.zeros(n, self.dtype)
        for name, values in columns.items():
            out[name] = values
        return out

    def renamed(self, name: str, description: str | None = None) -> SeriesDef:
        """The same entries under another name (e.g. a stage whose series name is a
        parameter)."""
        return SeriesDef(name, self.dtype,
                         self.description if description is None else description)

    def fields(self) -> str:
        """The field names, e.g. ``t, x, y, support, total``."""
        return ", ".join(self.dtype.names)


#: the camera's angular velocity in the FOE series, deg/s about its axes (x right, y down, z
#: forward; :class:`~evchain.core.truth.RotationTruth`'s convention)
ROTATION_FIELDS = ("wx_deg_s", "wy_deg_s", "wz_deg_s")

FOE = SeriesDef("foe", [("t", "i8"), ("x", "f8"), ("y", "f8"), ("support", "f8"),
                        ("total", "f8"), *((c, "f8") for c in ROTATION_FIELDS),
                        ("rotation", "i1")],
                "focus of expansion (the heading) estimates: x, y in px, support and total "
                "weight of the estimate; the camera's angular velocity wx, wy, wz in deg/s "
                "where rotation is 1 (fitted to the flow) or 2 (measured: the gyro's), else "
                "0 and rotation 0")
FOE_VOTES = FOE.renamed("foe_votes", "the voting FOE estimates (foe_map's foe entries) that "
                        "foe_fit refined")

TTC = SeriesDef("ttc", [("t", "i8"), ("tau_s", "f8"), ("cluster", "i8"), ("x", "f8"),
                        ("y", "f8"), ("support", "f8")],
                "time to contact of the obstacle's cluster per tick: tau_s in s, centre x, y "
                "in px")
TTC_CLUSTERS = SeriesDef("ttc_clusters", [("t", "i8"), ("cluster", "i8"), ("x", "f8"),
                                          ("y", "f8"), ("size_px", "f8"), ("tau_s", "f8"),
                                          ("support", "f8"), ("ground_ratio", "f8")],
                         "every live TTC cluster per tick")

FLOW_DENSITY = SeriesDef("flow_density", [("t", "i8"), ("n_in", "i8"), ("n_out", "i8")],
                         "input events and flow events per time bin (t = bin end)")
FLOW_ERROR = SeriesDef("flow_error", [("t", "i8"), ("n", "i8"), ("aee_pxs", "f8"),
                                      ("aee_normal_pxs", "f8"), ("aae_deg", "f8"),
                                      ("invalid_rate", "f8")],
                       "flow errors per time bin (t = bin end): px/s, degrees, share 0-1")
_ROTATION_TRUE = ("wx_true_deg_s", "wy_true_deg_s", "wz_true_deg_s")
FOE_ERROR = SeriesDef("foe_error", [("t", "i8"), ("x", "f8"), ("y", "f8"), ("x_true", "f8"),
                                    ("y_true", "f8"), ("dx", "f8"), ("dy", "f8"),
                                    ("angle_deg", "f8"),
                                    *((c, "f8") for c in ROTATION_FIELDS + _ROTATION_TRUE),
                                    ("rotation_error_deg_s", "f8")],
                      "per foe entry: estimate, truth and error in px, ray angle in degrees; "
                      "the estimated and the true angular velocity (0 where unknown) and the "
                      "norm of their difference in deg/s (-1 where either is unknown)")
TTC_ERROR = SeriesDef("ttc_error", [("t", "i8"), ("tau_s", "f8"), ("tau_true_s", "f8"),
                                    ("rel_error", "f8"), ("cluster", "i8"), ("x", "f8"),
                                    ("y", "f8"), ("on_obstacle", "i1")],
                      "per ttc entry: estimate, truth, relative error (both -1 where the "
                      "truth has no TTC: nothing ahead to contact), whether the cluster "
                      "lies on the obstacle (1, 0, -1 unknown)")
EVENT_RATE = SeriesDef("event_rate", [("t", "i8"), ("t_bin_start", "i8"), ("t_bin_end", "i8"),
                                      ("rate_eps", "f8"), ("on", "i8"), ("off", "i8")],
                       "events per second at one pixel column per bin")

IMU = SeriesDef("imu", [("t", "i8"), ("ax", "f8"), ("ay", "f8"), ("az", "f8"), ("gx", "f8"),
                        ("gy", "f8"), ("gz", "f8"), ("temperature_c", "f8")],
                "inertial samples in the camera's axes (x right, y down, z forward): "
                "accelerometer ax, ay, az in g (specific force: an upright camera at rest reads "
                "ay = -1), gyro gx, gy, gz in deg/s (right-handed: tilt up, pan right, roll "
                "clockwise seen from behind), temperature_c in °C")
IMU_RATE = SeriesDef("imu_rate", [("t", "i8"), ("n", "i8"), ("gx", "f8"), ("gy", "f8"),
                                  ("gz", "f8"), ("fit_gx", "f8"), ("fit_gy", "f8"),
                                  ("fit_gz", "f8"), ("normal_error", "f8"), ("valid", "i1")],
                     "per time bin (t = the bin's last µs): the gyro's rate (bias removed, at "
                     "the times the measurements reflect) and the rate fitted to the measured "
                     "normal flow, "
                     "deg/s; n measurements, their median relative normal-flow error against "
                     "the gyro's flow, and whether the gyro's flow is the truth there (1) or "
                     "not (0)")

#: default bin of the flow density series (µs)
DENSITY_BIN_US = 100_000


class DensityCounter:
    """Counts input and flow events per time bin ``[k B, (k+1) B)`` and emits
    :data:`FLOW_DENSITY` entries.

    Use in a flow filter: ``entries = counter.add(events.t, events.t[index], packet.t_end)`` (both
    time arrays sorted, as event times are) in ``process`` and ``counter.flush()`` at the end;
    append both to the output packet's series ``flow_density`` (always, even when empty). A bin
    is emitted, with ``t`` = its end, in the first packet whose slice reaches past its end, so
    entries do not depend on how the stream was cut; the last, partial bin comes from
    :meth:`flush`. Only bins with input events appear.
    """

    def __init__(self, bin_us: int = DENSITY_BIN_US):
        if bin_us <= 0:
            raise ConfigError(f"density bin must be > 0 us, got {bin_us}")
        self.bin_us = int(bin_us)
        self.reset()

    def reset(self) -> None:
        self.pending: dict[int, list[int]] = {}

    def add(self, t_in: np.ndarray, t_out: np.ndarray, t_end: int) -> np.ndarray:
        for times, col in ((t_in, 0), (t_out, 1)):
            if len(times):  # times are sorted: count per bin by bisection
                times = np.asarray(times, np.int64)
                k0 = int(times[0]) // self.bin_us
                k1 = int(times[-1]) // self.bin_us
                if k0 == k1:
                    self.pending.setdefault(k0, [0, 0])[col] += len(times)
                    continue
                cuts = np.searchsorted(times, np.arange(k0 + 1, k1 + 1) * self.bin_us)
                counts = np.diff(np.concatenate([[0], cuts, [len(times)]]))
                for kk, cc in zip(range(k0, k1 + 1), counts.tolist(), strict=True):
                    if cc:
                        self.pending.setdefault(kk, [0, 0])[col] += cc
        done = sorted(k for k in self.pending if (k + 1) * self.bin_us < t_end)
        return self._emit(done)

    def flush(self) -> np.ndarray:
        return self._emit(sorted(self.pending))

    def _emit(self, keys: list[int]) -> np.ndarray:
        rows = [(k, *self.pending.pop(k)) for k in keys]
        rows = [r for r in rows if r[1] > 0]
        return FLOW_DENSITY.array(t=np.array([(k + 1) * self.bin_us for k, _, _ in rows],
                                             np.int64),
                                  n_in=np.array([r[1] for r in rows], np.int64),
                                  n_out=np.array([r[2] for r in rows], np.int64))
