"""Detector maths in plain numpy: preprocessing, output decoders and NMS.

Nothing here knows GStreamer or ONNX Runtime: arrays in, arrays out, so every step can be
tested on small synthetic tensors. Boxes are ``x1, y1, x2, y2`` float32 rows; every decoder
returns them in pixels of the *frame* it was given (not of the network input), clipped to it.
Class indexes are 0-based indexes into the labels file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

LETTERBOX_GREY = 114  # Ultralytics pads with this value; the network was trained on it
DEFAULT_MAX_CANDIDATES = 1000  # bounds the NMS cost when a low threshold lets thousands through


class Objects(NamedTuple):
    """The objects found in one frame."""

    boxes: np.ndarray  # (K, 4) float32 x1, y1, x2, y2 in frame pixels
    scores: np.ndarray  # (K,) float32
    classes: np.ndarray  # (K,) int32, 0-based


# --- preprocessing -------------------------------------------------------------------------


def resize_into(frame: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Resize ``frame`` (H, W, 3 uint8) to fill ``dst`` (h, w, 3 uint8), writing into ``dst``."""
    return cv2.resize(frame, (dst.shape[1], dst.shape[0]), dst=dst, interpolation=cv2.INTER_LINEAR)


@dataclass(frozen=True)
class Letterbox:
    """Aspect-preserving fit of a frame into a network input, centred with grey bands."""

    scale: float
    pad_x: int
    pad_y: int
    width: int  # size of the scaled frame inside the input
    height: int

    @staticmethod
    def fit(frame_w: int, frame_h: int, input_w: int, input_h: int) -> "Letterbox":
        scale = min(input_w / frame_w, input_h / frame_h)
        width, height = max(1, round(frame_w * scale)), max(1, round(frame_h * scale))
        return Letterbox(scale, (input_w - width) // 2, (input_h - height) // 2, width, height)

    def to_frame(self, boxes: np.ndarray) -> np.ndarray:
        """Map x1, y1, x2, y2 boxes from input pixels back to frame pixels."""
        out = boxes - np.array([self.pad_x, self.pad_y, self.pad_x, self.pad_y], np.float32)
        return out / np.float32(self.scale)


def letterbox_into(frame: np.ndarray, canvas: np.ndarray, box: Letterbox) -> None:
    """Resize ``frame`` into ``canvas`` at ``box``; the grey bands must already be there."""
    inner = canvas[box.pad_y : box.pad_y + box.height, box.pad_x : box.pad_x + box.width]
    # cv2 writes into a strided view in place, so no intermediate image is made
    cv2.resize(frame, (box.width, box.height), dst=inner, interpolation=cv2.INTER_LINEAR)


def hwc_to_chw_unit(image: np.ndarray, dst: np.ndarray) -> None:
    """uint8 (H, W, 3) 0..255 -> float32 (3, H, W) 0..1, written into ``dst``."""
    np.multiply(image.transpose(2, 0, 1), np.float32(1 / 255), out=dst)


# --- NMS -----------------------------------------------------------------------------------


def iou_one_to_many(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one x1, y1, x2, y2 box against (K, 4) boxes."""
    x1 = np.maximum(box[0], boxes[:, 0])
    y1 = np.maximum(box[1], boxes[:, 1])
    x2 = np.minimum(box[2], boxes[:, 2])
    y2 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return inter / np.maximum(area + areas - inter, 1e-9)


def nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou: float) -> np.ndarray:
    """Class-wise greedy NMS; indexes of the boxes kept, best score first.

    Boxes of different classes never suppress each other: each class is shifted to its own
    region of the plane, so one pass over all boxes does every class at once.
    """
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    span = float(np.max(boxes) - np.min(boxes)) + 1.0
    shifted = boxes.astype(np.float64) + (classes.astype(np.float64) * span)[:, None]
    order = np.argsort(-scores, kind="stable")
    keep = []
    while order.size:
        best = order[0]
        keep.append(best)
        rest = order[1:]
        order = rest[iou_one_to_many(shifted[best], shifted[rest]) <= iou]
    return np.asarray(keep, np.int64)


def _finish(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, frame_w: int, frame_h: int,
            iou: float | None) -> Objects:
    """Clip to the frame, drop empty boxes, then NMS (``iou`` None: the model did it)."""
    boxes = boxes.astype(np.float32, copy=True)
    np.clip(boxes[:, 0::2], 0, frame_w, out=boxes[:, 0::2])
    np.clip(boxes[:, 1::2], 0, frame_h, out=boxes[:, 1::2])
    real = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    boxes, scores, classes = boxes[real], scores[real].astype(np.float32), classes[real].astype(np.int32)
    if iou is not None:
        keep = nms(boxes, scores, classes, iou)
        boxes, scores, classes = boxes[keep], scores[keep], classes[keep]
    else:
        order = np.argsort(-scores, kind="stable")
        boxes, scores, classes = boxes[order], scores[order], classes[order]
    return Objects(boxes, scores, classes)


# --- decoders ------------------------------------------------------------------------------


def decode_centernet(detections: np.ndarray, frame_w: int, frame_h: int, input_w: int, input_h: int,
                     threshold: float, iou: float) -> Objects:
    """CenterNet top-k rows ``x1, y1, x2, y2, score, class`` in input pixels, (100, 6).

    The input was a plain (aspect-changing) resize, so x and y scale separately. The model
    has no NMS and reports the same object at neighbouring peaks: NMS is applied here.
    """
    rows = detections.reshape(-1, 6)
    rows = rows[rows[:, 4] >= threshold]
    scale = np.array([frame_w / input_w, frame_h / input_h] * 2, np.float32)
    return _finish(rows[:, :4] * scale, rows[:, 4], rows[:, 5].astype(np.int32), frame_w, frame_h, iou)


def decode_ssd(num: float, boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray,
               frame_w: int, frame_h: int, threshold: float) -> Objects:
    """TF Object Detection API outputs of one image: normalised ``ymin, xmin, ymax, xmax``.

    Classes are 1-based in the model (0 is background); they are returned 0-based. NMS is
    part of the graph, so none is applied here.
    """
    n = int(num)
    keep = scores[:n] >= threshold
    yx = boxes[:n][keep]
    xyxy = yx[:, [1, 0, 3, 2]] * np.array([frame_w, frame_h, frame_w, frame_h], np.float32)
    cls = classes[:n][keep].astype(np.int32) - 1
    return _finish(xyxy, scores[:n][keep], cls, frame_w, frame_h, None)


def decode_yolo(output: np.ndarray, box: Letterbox, frame_w: int, frame_h: int, threshold: float,
                iou: float, max_candidates: int = DEFAULT_MAX_CANDIDATES) -> Objects:
    """Ultralytics YOLOv8/v11 head of one image: (4 + C, N), rows ``cx, cy, w, h`` in input
    pixels then C class scores (no objectness). Best class per anchor, threshold, NMS."""
    class_scores = output[4:]
    best = class_scores.max(axis=0)
    cand = np.flatnonzero(best >= threshold)
    if cand.size > max_candidates:
        cand = cand[np.argpartition(-best[cand], max_candidates)[:max_candidates]]
    cls = class_scores[:, cand].argmax(axis=0).astype(np.int32)
    cx, cy, w, h = output[:4, cand]
    xyxy = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    return _finish(box.to_frame(xyxy), best[cand], cls, frame_w, frame_h, iou)
