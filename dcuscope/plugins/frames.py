"""What travels with a frame: its identity, its detections, and the batch layout.

Identity and detections ride on ``GstReferenceTimestampMeta``: its reference caps carry typed
arrays, one entry per frame (identity) or per object (detections). Such a meta survives
copies, shallow copies and every stock element, can be read from Python and from C, and one
meta holds a whole batch, so no per-meta iteration is needed (PyGObject cannot iterate metas).

- identity ``timestamp/x-dcuscope-frames``: ``source``, ``frame``, ``origin`` arrays (int,
  guint64, guint64 ns), in slot order; the meta's own timestamp is the first origin.
- detections ``timestamp/x-dcuscope-objects``: ``slot``, ``class``, ``score``, ``x1``, ``y1``,
  ``x2``, ``y2``, ``label`` arrays, boxes in pixels of the buffer they are attached to.

A frame from an RTSP camera may also carry its capture time on the sender's clock, as
GStreamer's jitter buffer attaches it: a ``GstReferenceTimestampMeta`` with caps
``timestamp/x-ntp`` (ns since 1900), read by :func:`capture_ns`.

A batch (caps ``video/x-dcuscope-batch``) holds one ``GstMemory`` per frame, each a packed
RGB image of ``width`` x ``height`` (stride = width * 3), in slot order.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np

from dcuscope.core.gst import Gst, GstVideo

BATCH_MEDIA_TYPE = "video/x-dcuscope-batch"
FRAMES_MEDIA_TYPE = "timestamp/x-dcuscope-frames"
OBJECTS_MEDIA_TYPE = "timestamp/x-dcuscope-objects"
NTP_CAPS = Gst.Caps.from_string("timestamp/x-ntp")
DROP_MESSAGE = "dcuscope-drop"
"""Name of the element message an element posts for each frame it drops on purpose (see
:func:`drop_structure`); the probes turn it into a drop event."""
NTP_UNIX_OFFSET_NS = 2_208_988_800 * 1_000_000_000
"""From the NTP epoch (1900) to the Unix epoch (1970)."""
FRAMES_CAPS = Gst.Caps.from_string(FRAMES_MEDIA_TYPE)
OBJECTS_CAPS = Gst.Caps.from_string(OBJECTS_MEDIA_TYPE)
BATCH_TEMPLATE_CAPS = Gst.Caps.from_string(
    f"{BATCH_MEDIA_TYPE}, format=(string)RGB, width=(int)[1,32768], height=(int)[1,32768], "
    "batch-size=(int)[1,1024]"
)


@dataclass(frozen=True)
class FrameId:
    """Identity of one camera frame, fixed where it enters the pipeline."""

    source: int
    frame: int
    origin_ns: int


@dataclass
class Detections:
    """Objects found in the frames of one buffer; arrays share their first dimension."""

    slot: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    cls: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    score: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))
    labels: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.slot.shape[0])

    @staticmethod
    def concat(parts: Sequence["Detections"]) -> "Detections":
        parts = [p for p in parts if len(p)]
        if not parts:
            return Detections()
        return Detections(
            slot=np.concatenate([p.slot for p in parts]).astype(np.int32),
            cls=np.concatenate([p.cls for p in parts]).astype(np.int32),
            score=np.concatenate([p.score for p in parts]).astype(np.float32),
            boxes=np.concatenate([p.boxes for p in parts]).astype(np.float32),
            labels=[label for p in parts for label in p.labels],
        )

    def subset(self, keep: np.ndarray) -> "Detections":
        """The detections where the boolean mask ``keep`` is set."""
        return Detections(
            slot=self.slot[keep], cls=self.cls[keep], score=self.score[keep],
            boxes=self.boxes[keep], labels=[label for label, k in zip(self.labels, keep) if k],
        )

    def for_slot(self, slot: int) -> "Detections":
        return self.subset(self.slot == slot)


def _array(type_name: str, values: Sequence, fmt: str = "{}") -> str:
    return f"({type_name})< {', '.join(fmt.format(v) for v in values)} >" if len(values) else "(int)< >"


def _quote(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def write_frames(buf: Gst.Buffer, ids: Sequence[FrameId]) -> None:
    """Attach the identity of the frames ``buf`` holds (slot order). ``buf`` must be writable."""
    caps = Gst.Caps.from_string(
        f"{FRAMES_MEDIA_TYPE}, source={_array('int', [i.source for i in ids])}, "
        f"frame={_array('guint64', [i.frame for i in ids])}, "
        f"origin={_array('guint64', [i.origin_ns for i in ids])}"
    )
    buf.add_reference_timestamp_meta(caps, ids[0].origin_ns if ids else 0, Gst.CLOCK_TIME_NONE)


def read_frames(buf: Gst.Buffer) -> list[FrameId]:
    """The identities attached to ``buf``, in slot order; empty when none."""
    meta = buf.get_reference_timestamp_meta(FRAMES_CAPS)
    if meta is None:
        return []
    s = meta.reference[0]
    sources, frames, origins = s.get_value("source"), s.get_value("frame"), s.get_value("origin")
    if isinstance(sources, int):  # one frame as plain fields (the dcuscope GStreamer tracer writes so)
        sources, frames, origins = [sources], [frames], [origins or 0]
    return [FrameId(int(a), int(b), int(c)) for a, b, c in zip(sources, frames, origins)]


def capture_ns(buf: Gst.Buffer) -> int | None:
    """When the frame in ``buf`` was captured, on its sender's clock, as CLOCK_REALTIME ns: the
    ``timestamp/x-ntp`` meta an RTSP source's jitter buffer attaches (derived from the sender's
    RTCP reports: none before the first); None without it."""
    meta = buf.get_reference_timestamp_meta(NTP_CAPS)
    return None if meta is None else meta.timestamp - NTP_UNIX_OFFSET_NS


def write_objects(buf: Gst.Buffer, dets: Detections) -> None:
    """Attach ``dets`` to ``buf`` (writable); one meta, replacing nothing already there."""
    n = len(dets)
    caps = Gst.Caps.from_string(
        f"{OBJECTS_MEDIA_TYPE}, count=(int){n}, slot={_array('int', dets.slot.tolist())}, "
        f"class={_array('int', dets.cls.tolist())}, "
        f"score={_array('double', dets.score.tolist(), '{:.4f}')}, "
        + ", ".join(
            f"{k}={_array('double', dets.boxes[:, j].tolist(), '{:.2f}')}"
            for j, k in enumerate(("x1", "y1", "x2", "y2"))
        )
        + f", label=(string)< {', '.join(_quote(l) for l in dets.labels)} >"
    )
    buf.add_reference_timestamp_meta(caps, 0, Gst.CLOCK_TIME_NONE)


def read_objects(buf: Gst.Buffer) -> Detections:
    """The detections attached to ``buf``; empty when none."""
    meta = buf.get_reference_timestamp_meta(OBJECTS_CAPS)
    if meta is None:
        return Detections()
    s = meta.reference[0]
    if s.get_value("count") == 0:
        return Detections()
    boxes = np.stack([np.asarray(list(s.get_value(k)), np.float32) for k in ("x1", "y1", "x2", "y2")], 1)
    return Detections(
        slot=np.asarray(list(s.get_value("slot")), np.int32),
        cls=np.asarray(list(s.get_value("class")), np.int32),
        score=np.asarray(list(s.get_value("score")), np.float32),
        boxes=boxes,
        labels=[str(v) for v in s.get_value("label")],
    )


def batch_caps(width: int, height: int, batch_size: int, framerate: tuple[int, int] | None) -> Gst.Caps:
    """Caps of a batch of ``batch_size`` (at most) RGB frames of ``width`` x ``height``."""
    rate = f", framerate=(fraction){framerate[0]}/{framerate[1]}" if framerate else ""
    return Gst.Caps.from_string(
        f"{BATCH_MEDIA_TYPE}, format=(string)RGB, width=(int){width}, height=(int){height}, "
        f"batch-size=(int){batch_size}{rate}"
    )


@dataclass(frozen=True)
class BatchLayout:
    width: int
    height: int
    batch_size: int

    @staticmethod
    def from_caps(caps: Gst.Caps) -> "BatchLayout":
        s = caps[0]
        return BatchLayout(s.get_value("width"), s.get_value("height"), s.get_value("batch-size"))


@contextmanager
def mapped_batch(buf: Gst.Buffer, layout: BatchLayout, write: bool = False) -> Iterator[list[np.ndarray]]:
    """Map every frame of a batch as an (height, width, 3) uint8 array, zero-copy.

    The arrays are valid only inside the ``with`` block. ``write`` needs a writable buffer.
    """
    flags = Gst.MapFlags.READ | (Gst.MapFlags.WRITE if write else 0)
    mems, infos, arrays = [], [], []
    try:
        for i in range(buf.n_memory()):
            mem = buf.peek_memory(i)
            ok, info = mem.map(flags)
            if not ok:
                raise RuntimeError(f"cannot map frame {i} of a batch")
            mems.append(mem)
            infos.append(info)
            arrays.append(np.frombuffer(info.data, np.uint8).reshape(layout.height, layout.width, 3))
        yield arrays
    finally:
        del arrays
        for mem, info in zip(mems, infos):
            mem.unmap(info)


PACKED_CHANNELS = {"RGB": 3, "BGR": 3, "RGBA": 4, "BGRA": 4, "RGBx": 4, "BGRx": 4, "xRGB": 4,
                   "xBGR": 4, "ARGB": 4, "ABGR": 4, "GRAY8": 1}


@contextmanager
def mapped_video(buf: Gst.Buffer, info: GstVideo.VideoInfo, write: bool = False) -> Iterator[np.ndarray]:
    """Map a packed video frame as an (height, width, channels) uint8 array, zero-copy.

    Row padding (stride > width * channels) is honoured through a strided view. Valid only
    inside the ``with`` block; ``write`` needs a writable buffer.
    """
    fmt = info.finfo.name
    if fmt not in PACKED_CHANNELS:
        raise ValueError(f"format {fmt} is not a packed format")
    channels = PACKED_CHANNELS[fmt]
    flags = Gst.MapFlags.READ | (Gst.MapFlags.WRITE if write else 0)
    ok, mapinfo = buf.map(flags)
    if not ok:
        raise RuntimeError("cannot map video buffer")
    raw = frame = None  # so that a failure below is reported, not masked by the cleanup
    try:
        stride, height, width = info.stride[0], info.height, info.width
        raw = np.frombuffer(mapinfo.data, np.uint8, count=stride * height).reshape(height, stride)
        frame = raw[:, : width * channels].reshape(height, width, channels)
        yield frame
    finally:
        del raw, frame
        buf.unmap(mapinfo)


def drop_structure(frame: FrameId, reason: str, age_ns: int) -> Gst.Structure:
    """The ``dcuscope-drop`` message body for ``frame``, dropped for ``reason`` at ``age_ns``."""
    return Gst.Structure.from_string(
        f"{DROP_MESSAGE}, source=(int){frame.source}, frame=(guint64){frame.frame}, reason=(string){reason}, "
        f"age-ns=(gint64){age_ns}")[0]
