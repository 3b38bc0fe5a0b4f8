"""One video frame: events (flow by direction) with the overlays researchers expect.

Events on black (ON white, OFF blue-grey; flow events coloured by direction), magnified by
``scale``. With overlays: the FOE estimate (yellow plus) and truth (red plus) with a legend
naming them (top-right), a header line (top-left: stream time and the obstacle's TTC), on flow
frames sampled flow arrows and the colour wheel (bottom-right), and every live TTC cluster as a
square with its TTC as a label (the obstacle's in orange, first), placed so that no label
covers another, the header, the legend or the wheel (see :mod:`evchain.report.overlay`).
"""

from __future__ import annotations

import numpy as np

from evchain.report.overlay import (
    Box,
    draw_flow_arrows,
    draw_labels,
    draw_legend,
    draw_text,
    paste_wheel,
)
from evchain.report.render import RED, YELLOW, draw_cross, event_image

OBSTACLE = (255, 150, 0)
CLUSTER = (190, 190, 190)


def compose(events, scale: int, overlay: bool = True, foe=(np.nan, np.nan), foe_true=None,
            header: str = "", clusters: np.ndarray | None = None, obstacle: int | None = None,
            arrows_every_px: int = 16) -> tuple[np.ndarray, list[Box | None]]:
    """The frame (RGB uint8 ``[H*scale, W*scale, 3]``) and the boxes of the cluster labels
    (None for a label with no free place). ``events``: an EventPacket or FlowPacket;
    ``clusters``: ``ttc_clusters`` entries of one tick; ``obstacle``: the ``ttc`` series'
    cluster id."""
    g = events.geometry
    flow = hasattr(events, "vx")
    img = event_image(g.height, g.width, events.x, events.y, events.p,
                      *((events.vx, events.vy) if flow else (None, None)))
    if overlay:
        if foe_true is not None:
            draw_cross(img, *foe_true, RED)
        draw_cross(img, *foe, YELLOW)
    img = np.kron(img, np.ones((scale, scale, 1), np.uint8))
    if not overlay:
        return img, []
    taken: list[Box] = []
    if flow:
        img = draw_flow_arrows(img, events.x, events.y, events.vx, events.vy, scale,
                               arrows_every_px)
        box = paste_wheel(img)
        if box is not None:
            taken.append(box)
    entries = []
    if np.isfinite(foe).all():
        entries.append((YELLOW, "FOE estimate"))
    if foe_true is not None and np.isfinite(foe_true).all():
        entries.append((RED, "FOE truth"))
    img, box = draw_legend(img, entries)
    if box is not None:
        taken.append(box)
    if header:
        img, box = draw_text(img, (2, 2), header)
        taken.append(box)
    if clusters is None or not len(clusters):
        return img, []
    return _clusters(img, clusters, obstacle, scale, taken)


def _clusters(img, clusters, obstacle, scale, taken):
    from PIL import Image, ImageDraw

    live = clusters[np.isfinite(clusters["tau_s"]) & (clusters["tau_s"] > 0)]
    first = live["cluster"] == (-1 if obstacle is None else obstacle)
    live = np.concatenate([live[first], np.sort(live[~first], order="support")[::-1]])
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    colours = [OBSTACLE if c == obstacle else CLUSTER for c in live["cluster"]]
    anchors = []
    for c, colour in zip(live, colours, strict=True):
        cx, cy = (c["x"] + 0.5) * scale, (c["y"] + 0.5) * scale
        half = max(1.0, c["size_px"] * scale)
        draw.rectangle([cx - half, cy - half, cx + half, cy + half], outline=colour)
        anchors.append((cx + half, cy))
    img = np.asarray(pil).copy()
    return draw_labels(img, anchors, [f"{tau:.2f} s" for tau in live["tau_s"]], colours, taken)
