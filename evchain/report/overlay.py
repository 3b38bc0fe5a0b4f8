"""Annotations drawn on RGB uint8 pictures (flow pictures, video frames), in output pixels.

* :func:`draw_flow_arrows`: sampled flow vectors, one arrow per occupied grid cell, as jAER
  and DV draw flow: the cell's mean flow, centred on the cell, length by speed (the 95th
  percentile of the picture's cell speeds fills 90 % of a cell; slower ones shorter, at least
  4 px), white with a two-stroke head at the tip;
* :func:`paste_wheel`: the colour-wheel legend of flow directions (bottom-right corner);
* :func:`draw_legend`: marker swatches with names (e.g. FOE estimate and truth), top-right;
* :func:`place_labels` / :func:`draw_labels`: text labels next to their points (e.g. TTC per
  cluster), each put at the first of eight positions around its point (right, left, then the
  rows above and below) that stays inside the picture and overlaps no label or box placed
  before; a label with no free position is left out.

Boxes are ``(x0, y0, x1, y1)`` with exclusive ends.
"""

from __future__ import annotations

import numpy as np

WHITE = (255, 255, 255)
BACKGROUND = (30, 30, 30)  # of legends and labels
Box = tuple[int, int, int, int]


def default_font():
    from PIL import ImageFont

    return ImageFont.load_default()


def text_size(text: str) -> tuple[int, int]:
    """Width and height of ``text`` in the default font, with a 1 px margin all round."""
    from PIL import Image, ImageDraw

    x0, y0, x1, y1 = ImageDraw.Draw(Image.new("RGB", (1, 1))).textbbox((0, 0), text,
                                                                       font=default_font())
    return x1 + 2, y1 + 2


def draw_text(img: np.ndarray, xy: tuple[int, int], text: str, colour=WHITE
              ) -> tuple[np.ndarray, Box]:
    """``text`` on a dark box with its top-left corner at ``xy``; returns the picture and the
    box."""
    from PIL import Image, ImageDraw

    w, h = text_size(text)
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    draw.rectangle([xy[0], xy[1], xy[0] + w - 1, xy[1] + h - 1], fill=BACKGROUND)
    draw.text((xy[0] + 1, xy[1]), text, fill=colour, font=default_font())
    return np.asarray(pil).copy(), (xy[0], xy[1], xy[0] + w, xy[1] + h)


def overlaps(a: Box, b: Box) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def flow_cells(x, y, vx, vy, width: int, height: int, cell: int):
    """Mean flow per occupied ``cell`` x ``cell`` block (sensor pixels): centres cx, cy and
    mean vx, vy, one entry per block with events."""
    nx, ny = -(-width // cell), -(-height // cell)
    flat = (np.asarray(y, np.int64) // cell) * nx + np.asarray(x, np.int64) // cell
    n = np.bincount(flat, minlength=nx * ny)
    sx = np.bincount(flat, np.asarray(vx, np.float64), nx * ny)
    sy = np.bincount(flat, np.asarray(vy, np.float64), nx * ny)
    k = np.flatnonzero(n)
    cx = (k % nx) * cell + (min(cell, width) - 1) / 2
    cy = (k // nx) * cell + (min(cell, height) - 1) / 2
    return cx, cy, sx[k] / n[k], sy[k] / n[k]


def draw_flow_arrows(img: np.ndarray, x, y, vx, vy, scale: int, spacing_px: int,
                     colour=WHITE) -> np.ndarray:
    """``img`` (sensor size times ``scale``) with one arrow per ``spacing_px`` output pixels
    of grid cell holding flow events; ``spacing_px`` 0 draws none."""
    if spacing_px <= 0 or not len(x):
        return img
    from PIL import Image, ImageDraw

    h, w = img.shape[0] // scale, img.shape[1] // scale
    cell = max(1, round(spacing_px / scale))
    cx, cy, mx, my = flow_cells(x, y, vx, vy, w, h, cell)
    speed = np.hypot(mx, my)
    keep = speed > 0
    if not keep.any():
        return img
    cx, cy, mx, my, speed = cx[keep], cy[keep], mx[keep], my[keep], speed[keep]
    ref = float(np.percentile(speed, 95))
    span = cell * scale
    length = np.maximum(0.9 * span * np.minimum(speed / ref, 1.0), 4.0)
    ux, uy = mx / speed, my / speed
    px, py = (cx + 0.5) * scale - 0.5, (cy + 0.5) * scale - 0.5  # cell centre, output px
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    for i in range(len(px)):
        half = length[i] / 2
        tail = (px[i] - ux[i] * half, py[i] - uy[i] * half)
        tip = (px[i] + ux[i] * half, py[i] + uy[i] * half)
        draw.line([tail, tip], fill=colour)
        head = max(2.0, length[i] / 3)
        for turn in (2.6, -2.6):  # about +-150 degrees from the direction
            c, s = np.cos(turn), np.sin(turn)
            draw.line([tip, (tip[0] + head * (c * ux[i] - s * uy[i]),
                             tip[1] + head * (s * ux[i] + c * uy[i]))], fill=colour)
    return np.asarray(pil).copy()


def wheel_box(shape: tuple[int, ...]) -> Box | None:
    """Where :func:`paste_wheel` puts the wheel in a picture of ``shape`` (None: too small)."""
    h, w = shape[:2]
    size = max(15, min(h, w) // 6) | 1
    if size + 4 > min(h, w):
        return None
    return (w - size - 2, h - size - 2, w - 2, h - 2)


def paste_wheel(img: np.ndarray) -> Box | None:
    """Paste the colour wheel of flow directions into the bottom-right corner (in place);
    returns its box."""
    from evchain.report.render import colour_wheel

    box = wheel_box(img.shape)
    if box is not None:
        legend = colour_wheel(box[2] - box[0])
        mask = legend.any(axis=-1)
        region = img[box[1]:box[3], box[0]:box[2]]
        region[mask] = legend[mask]
    return box


def draw_legend(img: np.ndarray, entries: list[tuple[tuple[int, int, int], str]]
                ) -> tuple[np.ndarray, Box | None]:
    """A legend in the top-right corner: per entry a plus-sign swatch in its colour and its
    name, on a dark box. Returns the picture and the box (None if nothing drawn)."""
    if not entries:
        return img, None
    from PIL import Image, ImageDraw

    sizes = [text_size(text) for _, text in entries]
    row = max(9, max(s[1] for s in sizes))
    width = 12 + max(s[0] for s in sizes) + 2
    height = row * len(entries) + 2
    h, w = img.shape[:2]
    if width + 2 > w or height + 2 > h:
        return img, None
    box = (w - width - 2, 2, w - 2, 2 + height)
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    draw.rectangle([box[0], box[1], box[2] - 1, box[3] - 1], fill=BACKGROUND)
    for k, (colour, text) in enumerate(entries):
        top = box[1] + 1 + k * row
        mx, my = box[0] + 5, top + row // 2
        draw.line([(mx - 3, my), (mx + 3, my)], fill=colour)
        draw.line([(mx, my - 3), (mx, my + 3)], fill=colour)
        draw.text((box[0] + 12, top), text, fill=WHITE, font=default_font())
    return np.asarray(pil).copy(), box


def place_labels(anchors: list[tuple[float, float]], sizes: list[tuple[int, int]],
                 width: int, height: int, taken: list[Box] = (), gap: int = 3
                 ) -> list[Box | None]:
    """A box per label, in order (earlier labels win): the first of eight positions around its
    anchor (right, left, upper right, upper left, lower right, lower left, above, below) inside
    ``width`` x ``height`` that overlaps neither ``taken`` nor an earlier label; None if there
    is none."""
    placed: list[Box] = list(taken)
    out: list[Box | None] = []
    for (ax, ay), (tw, th) in zip(anchors, sizes, strict=True):
        ax, ay = int(round(ax)), int(round(ay))
        mid, up, down = ay - th // 2, ay - th // 2 - th - 1, ay - th // 2 + th + 1
        right, left, centre = ax + gap, ax - gap - tw, ax - tw // 2
        candidates = [(right, mid), (left, mid), (right, up), (left, up), (right, down),
                      (left, down), (centre, up), (centre, down)]
        choice = None
        for x0, y0 in candidates:
            box = (x0, y0, x0 + tw, y0 + th)
            if (x0 >= 0 and y0 >= 0 and box[2] <= width and box[3] <= height
                    and not any(overlaps(box, b) for b in placed)):
                choice = box
                break
        out.append(choice)
        if choice is not None:
            placed.append(choice)
    return out


def draw_labels(img: np.ndarray, anchors: list[tuple[float, float]], texts: list[str],
                colours: list[tuple[int, int, int]], taken: list[Box] = ()
                ) -> tuple[np.ndarray, list[Box | None]]:
    """Labels on dark boxes placed by :func:`place_labels`; returns the picture and the
    boxes (None for a label left out)."""
    if not texts:
        return img, []
    from PIL import Image, ImageDraw

    boxes = place_labels(anchors, [text_size(t) for t in texts], img.shape[1], img.shape[0],
                         taken)
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    for box, text, colour in zip(boxes, texts, colours, strict=True):
        if box is not None:
            draw.rectangle([box[0], box[1], box[2] - 1, box[3] - 1], fill=BACKGROUND)
            draw.text((box[0] + 1, box[1]), text, fill=colour, font=default_font())
    return np.asarray(pil).copy(), boxes
