"""Pictures of FOE and TTC results (thesis Figs. 4.8/4.9 and 4.12-4.14), written atomically.

matplotlib with the Agg backend, imported lazily; every function writes one PNG through
:func:`evchain.io.atomic.atomic_write_bytes`, so a failed run never leaves a half-written file.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from evchain.io.atomic import atomic_write_bytes


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path, dpi: int = 110) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    _plt().close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def plot_foe_error(t_s: np.ndarray, dx: np.ndarray, dy: np.ndarray, path: str | Path,
                   title: str = "FOE error", warmup_s: float | None = None) -> Path:
    """|dx| and |dy| in px over time (as thesis Figs. 4.8 and 4.9)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(t_s, np.abs(dx), lw=1, label="|Δx| (px)")
    ax.plot(t_s, np.abs(dy), lw=1, label="|Δy| (px)")
    if warmup_s is not None and len(t_s):
        ax.axvspan(float(np.min(t_s)), warmup_s, color="0.85", label="warm-up")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("FOE error (px)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right")
    fig.tight_layout()
    return _save(fig, path)


def plot_ttc(t_s: np.ndarray, tau_s: np.ndarray, t_true_s: np.ndarray, tau_true_s: np.ndarray,
             path: str | Path, title: str = "Time to contact",
             on_obstacle: np.ndarray | None = None) -> Path:
    """Estimated TTC (dots) against the ground truth (line), relative error below.
    ``on_obstacle`` (per estimate: 1 on the obstacle, 0 off it, -1 unknown) colours the dots
    of estimates on and off the obstacle apart."""
    plt = _plt()
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(7, 5), sharex=True,
                                  gridspec_kw={"height_ratios": [2, 1]})
    ax.plot(t_true_s, tau_true_s, "r-", lw=1.5, label="ground truth")
    if on_obstacle is None or not (np.asarray(on_obstacle) >= 0).any():
        groups = [(np.ones(len(t_s), bool), "tab:blue", "estimate")]
    else:
        on = np.asarray(on_obstacle)
        groups = [(on == 1, "tab:blue", "estimate on the obstacle"),
                  (on != 1, "tab:orange", "estimate off the obstacle")]
    for k, color, label in groups:
        ax.plot(t_s[k], tau_s[k], ".", ms=2, color=color, label=label)
    finite = tau_true_s[np.isfinite(tau_true_s)]
    if len(finite):
        ax.set_ylim(0, 1.3 * float(np.max(finite)))
    ax.set_ylabel("TTC (s)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right")
    if len(t_s):
        tau_at = np.interp(t_s, t_true_s, tau_true_s) if len(t_true_s) else np.full_like(t_s,
                                                                                        np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.abs(tau_s - tau_at) / tau_at
        for k, color, _ in groups:
            ax2.plot(t_s[k], 100 * rel[k], ".", ms=2, color=color)
    for level in (10, 20):
        ax2.axhline(level, color="0.5", lw=0.8, ls="--")
    ax2.set_ylim(0, 100)
    ax2.set_ylabel("rel. error (%)")
    ax2.set_xlabel("time (s)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def plot_snapshot(width: int, height: int, x: np.ndarray, y: np.ndarray, vx: np.ndarray,
                  vy: np.ndarray, foe_est: tuple[float, float] | None,
                  foe_true: tuple[float, float] | None, clusters: np.ndarray | None,
                  path: str | Path, title: str = "") -> Path:
    """A frame-sized picture: flow events coloured by direction (hue), the estimated FOE (yellow
    circle), the true FOE (red diamond) and the TTC clusters labelled with tau (thesis Figs.
    4.12-4.14). ``clusters``: structured array with x, y, size_px, tau_s (and cluster)."""
    plt = _plt()
    from matplotlib.colors import hsv_to_rgb

    img = np.zeros((height, width, 3))
    if len(x):
        hue = (np.arctan2(vy, vx) / (2 * np.pi)) % 1.0
        rgb = hsv_to_rgb(np.stack([hue, np.ones_like(hue), np.ones_like(hue)], axis=-1))
        img[y.astype(int), x.astype(int)] = rgb
    scale = max(1.0, 640 / width)
    fig = plt.figure(figsize=(width * scale / 100, height * scale / 100 + 0.4))
    ax = fig.add_axes([0, 0, 1, height / (height + 40 / scale)])
    ax.imshow(img, interpolation="nearest", origin="upper")
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_axis_off()
    if clusters is not None:
        from matplotlib.patches import Rectangle

        for c in clusters:
            s = float(c["size_px"])
            ax.add_patch(Rectangle((c["x"] - s, c["y"] - s), 2 * s, 2 * s, fill=False,
                                   ec="white", lw=1))
            ax.text(c["x"] - s, c["y"] - s - 1, f"{c['tau_s']:.2f} s", color="white",
                    fontsize=7, va="bottom")
    if foe_true is not None and np.all(np.isfinite(foe_true)):
        ax.plot(*foe_true, marker="D", ms=7, mfc="none", mec="red", mew=2)
    if foe_est is not None and np.all(np.isfinite(foe_est)):
        ax.plot(*foe_est, marker="o", ms=8, mfc="none", mec="yellow", mew=2)
    fig.suptitle(title, fontsize=9, y=0.995)
    return _save(fig, path)
