"""Event rate at one pixel column over time (thesis Fig. 4.3), as a series and a PNG plot."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from evchain.io.atomic import atomic_write_bytes


def plot_event_rate(series: np.ndarray, path: str | Path, title: str = "",
                    label: str = "") -> None:
    """Write a PNG (atomically) of ``rate_eps`` in keps against the bin centre in seconds."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    tc = 0.5 * (series["t_bin_start"] + series["t_bin_end"]) * 1e-6
    ax.plot(tc, series["rate_eps"] * 1e-3, label=label or None)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("event rate [keps]")
    if title:
        ax.set_title(title)
    if label:
        ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
