"""Tiling maths for the tiler: grid shape, tile rectangles, collage composition, box mapping.

Plain numpy + OpenCV, no GStreamer: the tiler element only maps buffers and calls these.
A frame's tile is its source id (as in nvmultistreamtiler), so a camera keeps its place in
the collage when another camera's frame is missing from a batch.
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from dcuscope.plugins.colorspace import interpolation_for


def grid_shape(n: int, rows: int = 0, columns: int = 0) -> tuple[int, int]:
    """(rows, columns) for ``n`` sources; 0 means automatic (near-square, wider than tall)."""
    n = max(int(n), 1)
    if rows > 0 and columns > 0:
        return rows, columns
    if rows > 0:
        return rows, math.ceil(n / rows)
    if columns > 0:
        return math.ceil(n / columns), columns
    columns = math.ceil(math.sqrt(n))
    return math.ceil(n / columns), columns


def tile_rects(rows: int, columns: int, width: int, height: int) -> np.ndarray:
    """(rows * columns, 4) int array of tile (x, y, w, h), row-major.

    Edges are spread as ``i * width // columns`` so the tiles cover the whole collage even
    when the size does not divide evenly (tiles then differ by one pixel).
    """
    xs = np.arange(columns + 1) * width // columns
    ys = np.arange(rows + 1) * height // rows
    rects = np.empty((rows * columns, 4), np.int64)
    for r in range(rows):
        for c in range(columns):
            rects[r * columns + c] = (xs[c], ys[r], xs[c + 1] - xs[c], ys[r + 1] - ys[r])
    return rects


def tiles_for_slots(sources: Sequence[int], n_slots: int, n_tiles: int) -> np.ndarray:
    """Tile index of each slot of a batch: its source id, or -1 when it does not fit.

    Slots past the known identities (a batch without frame identity) use their slot index.
    """
    tiles = np.arange(n_slots, dtype=np.int64)
    known = min(len(sources), n_slots)
    tiles[:known] = np.asarray(sources[:known], np.int64)
    tiles[(tiles < 0) | (tiles >= n_tiles)] = -1
    return tiles


def compose(frames: Sequence[np.ndarray], tiles: np.ndarray, rects: np.ndarray, out: np.ndarray,
            blank_empty: bool = True) -> np.ndarray:
    """Scale each frame into its tile of ``out`` (H, W, C), in place; returns which tiles were filled.

    With ``blank_empty`` the tiles no frame claimed become black (``out`` may hold stale data,
    e.g. a pooled buffer); without it they keep what ``out`` held. When two frames claim the
    same tile the later one wins.
    """
    filled = np.zeros(len(rects), bool)
    for frame, tile in zip(frames, tiles):
        if tile < 0:
            continue
        x, y, w, h = (int(v) for v in rects[tile])
        view = out[y : y + h, x : x + w]
        fh, fw = frame.shape[:2]
        if (fw, fh) == (w, h):
            np.copyto(view, frame)
        else:
            # dst= makes OpenCV write straight into the collage; it returns a new array only
            # if it could not use dst, which would be a silent loss without this check.
            res = cv2.resize(frame, (w, h), dst=view, interpolation=interpolation_for(fw, fh, w, h))
            if res is not view:
                np.copyto(view, res)
        filled[tile] = True
    if blank_empty:
        for tile in np.flatnonzero(~filled):
            x, y, w, h = (int(v) for v in rects[tile])
            out[y : y + h, x : x + w] = 0
    return filled


def map_boxes(
    boxes: np.ndarray, slots: np.ndarray, tiles: np.ndarray, rects: np.ndarray, frame_w: int, frame_h: int
) -> tuple[np.ndarray, np.ndarray]:
    """Map boxes from frame pixels into collage pixels.

    ``boxes`` (N, 4) x1, y1, x2, y2 in the pixels of a ``frame_w`` x ``frame_h`` frame of slot
    ``slots[i]``; ``tiles`` from :func:`tiles_for_slots`. Returns (mapped boxes, keep mask):
    boxes of frames left out of the collage (or of unknown slots) are dropped. Mapped boxes are
    clipped to their tile.
    """
    slots = np.asarray(slots, np.int64)
    valid = (slots >= 0) & (slots < len(tiles))
    tile = np.full(len(slots), -1, np.int64)
    tile[valid] = tiles[slots[valid]]
    keep = tile >= 0
    r = rects[tile[keep]].astype(np.float32)
    sx = r[:, 2] / np.float32(frame_w)
    sy = r[:, 3] / np.float32(frame_h)
    b = np.asarray(boxes, np.float32)[keep]
    mapped = np.empty_like(b)
    mapped[:, 0] = r[:, 0] + np.clip(b[:, 0], 0, frame_w) * sx
    mapped[:, 1] = r[:, 1] + np.clip(b[:, 1], 0, frame_h) * sy
    mapped[:, 2] = r[:, 0] + np.clip(b[:, 2], 0, frame_w) * sx
    mapped[:, 3] = r[:, 1] + np.clip(b[:, 3], 0, frame_h) * sy
    return mapped, keep
