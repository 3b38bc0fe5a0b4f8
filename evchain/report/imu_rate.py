"""The rotation rate fitted to the measured flow against the gyro's, over time (a PNG)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from evchain.io.atomic import atomic_write_bytes


def plot_imu_rate(series: np.ndarray, path: str | Path, title: str = "") -> None:
    """Write a PNG (atomically): per camera axis (tilt x, pan y, roll z) the gyro's rate and
    the rate fitted to the measured normal flow (deg/s, ``imu_rate`` entries) against time;
    bins where the gyro's flow is no truth are shaded."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    t = series["t"] * 1e-6
    fig, axes = plt.subplots(3, 1, figsize=(7.0, 6.4), dpi=100, sharex=True)
    bin_s = float(np.median(np.diff(t))) if len(t) > 1 else 0.1
    for ax, axis, name in zip(axes, "xyz", ("tilt (x)", "pan (y)", "roll (z)"), strict=True):
        ax.plot(t, series[f"g{axis}"], "-", color="tab:blue", label="gyro")
        ax.plot(t, series[f"fit_g{axis}"], "o", ms=3, color="tab:orange",
                label="fitted to the measured flow")
        for tb in t[series["valid"] == 0]:
            ax.axvspan(tb - bin_s, tb, color="0.85", lw=0)
        ax.set_ylabel(f"{name} [deg/s]")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize="small")
    axes[-1].set_xlabel("time [s] (grey: no truth)")
    if title:
        axes[0].set_title(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
