"""Drawing for the osd element: boxes, labels with scores, a colour per class, a clock.

Plain numpy + OpenCV on an (H, W, C) uint8 view, usually straight into a mapped buffer. Colours
are defined as RGB and put into the frame's channel order by :func:`class_color`.
"""

from __future__ import annotations

import time
from typing import Sequence

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX

# 20 well-separated RGB colours (Tableau/d3 category20 order); class c gets PALETTE[c % 20],
# so a class has the same colour in every frame, stream and run.
PALETTE = np.array([
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
    (174, 199, 232), (255, 187, 120), (152, 223, 138), (255, 152, 150), (197, 176, 213),
    (196, 156, 148), (247, 182, 210), (199, 199, 199), (219, 219, 141), (158, 218, 229),
], np.uint8)

# Where R, G, B go in a pixel of each format, and how many channels it has.
LAYOUT = {"RGB": ((0, 1, 2), 3), "BGR": ((2, 1, 0), 3), "RGBA": ((0, 1, 2), 4), "RGBx": ((0, 1, 2), 4),
          "BGRA": ((2, 1, 0), 4), "BGRx": ((2, 1, 0), 4)}
FORMATS = tuple(LAYOUT)


def to_format(rgb: Sequence[int], fmt: str) -> tuple[int, ...]:
    """An RGB colour as the pixel value of ``fmt`` (channel order; opaque alpha for 4 channels)."""
    if fmt not in LAYOUT:
        raise ValueError(f"cannot draw on {fmt}; use one of {', '.join(FORMATS)}")
    order, channels = LAYOUT[fmt]
    pixel = tuple(int(rgb[i]) for i in order)
    return pixel + (255,) if channels == 4 else pixel


def class_color(cls: int, fmt: str = "RGB") -> tuple[int, ...]:
    """The colour of class ``cls`` as a pixel of ``fmt``."""
    return to_format(PALETTE[int(cls) % len(PALETTE)], fmt)


def _text_color(rgb: Sequence[int]) -> tuple[int, int, int]:
    # Black on light backgrounds, white on dark ones (BT.601 luma).
    return (0, 0, 0) if 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2] > 140 else (255, 255, 255)


def label_text(label: str, cls: int, score: float) -> str:
    return f"{label or f'class {cls}'} {score:.2f}"


def draw_label(img: np.ndarray, text: str, x: int, y: int, rgb: Sequence[int], fmt: str,
               font_scale: float) -> None:
    """``text`` on a filled ``rgb`` background whose bottom-left corner is (x, y); moved below
    ``y`` when there is no room above it."""
    thickness = max(1, round(font_scale * 2))
    (tw, th), base = cv2.getTextSize(text, FONT, font_scale, thickness)
    top = y - th - base - 2
    if top < 0:
        top = y
    cv2.rectangle(img, (x, top), (x + tw + 2, top + th + base + 2), to_format(rgb, fmt), cv2.FILLED)
    cv2.putText(img, text, (x + 1, top + th + 1), FONT, font_scale, to_format(_text_color(rgb), fmt),
                thickness, cv2.LINE_AA)


def draw_detections(img: np.ndarray, fmt: str, boxes: np.ndarray, classes: np.ndarray, scores: np.ndarray,
                    labels: Sequence[str], line_width: int = 2, display_text: bool = True,
                    font_scale: float = 0.5) -> None:
    """Draw each box (x1, y1, x2, y2 pixels) in its class colour, with ``label score`` above it."""
    for i, (x1, y1, x2, y2) in enumerate(np.rint(np.asarray(boxes, np.float64)).astype(int)):
        rgb = PALETTE[int(classes[i]) % len(PALETTE)]
        cv2.rectangle(img, (x1, y1), (x2, y2), to_format(rgb, fmt), line_width)
        if display_text:
            label = labels[i] if i < len(labels) else ""
            draw_label(img, label_text(label, int(classes[i]), float(scores[i])), x1 - line_width // 2,
                       y1 - (line_width + 1) // 2, rgb, fmt, font_scale)


def clock_text(ns: int) -> str:
    """Local wall-clock time of ``ns`` (ns since the epoch) as HH:MM:SS.mmm."""
    seconds, rest = divmod(ns, 1_000_000_000)
    return time.strftime("%H:%M:%S", time.localtime(seconds)) + f".{rest // 1_000_000:03d}"


def draw_clock(img: np.ndarray, fmt: str, text: str, font_scale: float = 0.5) -> None:
    """``text`` in white on black in the top-left corner."""
    thickness = max(1, round(font_scale * 2))
    (tw, th), base = cv2.getTextSize(text, FONT, font_scale, thickness)
    cv2.rectangle(img, (0, 0), (tw + 8, th + base + 8), to_format((0, 0, 0), fmt), cv2.FILLED)
    cv2.putText(img, text, (4, th + 4), FONT, font_scale, to_format((255, 255, 255), fmt), thickness, cv2.LINE_AA)
