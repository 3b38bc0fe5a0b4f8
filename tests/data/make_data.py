"""Make the small AEDAT 2.0 test file ``moving_edge_davis240.aedat`` (run from anywhere).

A bright 40x40 px square moves at (100, 50) px/s for 1 s across a DAVIS240 sensor (240x180):
pixels the square enters fire ON, pixels it leaves fire OFF, at the time the edge passes the
pixel centre (sampled every 0.5 ms, with a random sub-step offset). 2000 uniform noise events
(random polarity) are mixed in, and a hot pixel at (200, 20) fires ON every 250 µs (what the
quick start's refractory stage thins out). Deterministic (fixed seed); 18 000 events, ~145 kB.

    python tests/data/make_data.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evchain.core.packets import EventPacket, Geometry
from evchain.io.aedat2 import write_aedat2

OUT = Path(__file__).with_name("moving_edge_davis240.aedat")
SIZE_PX = 40
START_PX = (40.0, 60.0)          # top-left corner of the square at t = 0 (evchain: top-left)
VELOCITY_PXS = (100.0, 50.0)
DURATION_US = 1_000_000
STEP_US = 500
NOISE_EVENTS = 2000
HOT_PIXEL = (200, 20)
HOT_PERIOD_US = 250
SEED = 42


def square_events(geometry: Geometry, rng: np.random.Generator):
    ys, xs = np.mgrid[0:geometry.height, 0:geometry.width]
    xc, yc = xs + 0.5, ys + 0.5  # pixel centres in edge coordinates

    def inside(t_us: float) -> np.ndarray:
        x0 = START_PX[0] + VELOCITY_PXS[0] * t_us * 1e-6
        y0 = START_PX[1] + VELOCITY_PXS[1] * t_us * 1e-6
        return (xc >= x0) & (xc < x0 + SIZE_PX) & (yc >= y0) & (yc < y0 + SIZE_PX)

    parts = []
    before = inside(0.0)
    for t in range(STEP_US, DURATION_US + 1, STEP_US):
        now = inside(float(t))
        for mask, pol in ((now & ~before, 1), (before & ~now, -1)):
            yy, xx = np.nonzero(mask)
            tt = t - rng.integers(0, STEP_US, len(xx))
            parts.append((xx, yy, tt, np.full(len(xx), pol)))
        before = now
    return [np.concatenate(c) for c in zip(*parts, strict=True)]


def make(path: Path = OUT) -> Path:
    rng = np.random.default_rng(SEED)
    g = Geometry(240, 180)
    x, y, t, p = square_events(g, rng)
    x = np.concatenate([x, rng.integers(0, g.width, NOISE_EVENTS)])
    y = np.concatenate([y, rng.integers(0, g.height, NOISE_EVENTS)])
    t = np.concatenate([t, rng.integers(0, DURATION_US, NOISE_EVENTS)])
    p = np.concatenate([p, rng.choice([-1, 1], NOISE_EVENTS)])
    hot_t = np.arange(0, DURATION_US, HOT_PERIOD_US)
    x = np.concatenate([x, np.full(len(hot_t), HOT_PIXEL[0])])
    y = np.concatenate([y, np.full(len(hot_t), HOT_PIXEL[1])])
    t = np.concatenate([t, hot_t])
    p = np.concatenate([p, np.ones(len(hot_t), np.int64)])
    order = np.lexsort((x, y, t))
    ev = EventPacket(geometry=g, t_start=0, t_end=DURATION_US,
                     x=x[order].astype(np.uint16), y=y[order].astype(np.uint16),
                     t=t[order].astype(np.int64), p=p[order].astype(np.int8)).validate()
    return write_aedat2(path, ev, chip="davis240")


if __name__ == "__main__":
    out = make()
    print(f"wrote {out} ({out.stat().st_size} bytes)")
