"""mux: N camera streams -> one batch of frames (nvstreammux counterpart).

Each request pad ``sink_%u`` takes RGB frames of any size; a batch takes, from every pad
whose next frame is due (running time within one frame period of the earliest), one frame,
scaled to ``width`` x ``height`` when it is not that size already. Frames that already have
the batch size are not copied: the batch buffer shares their memory, one GstMemory per frame.
A stream that reaches EOS drops out while the others go on. With live sources the batch is
pushed after ``batched-push-timeout`` even if some cameras have nothing (a dead camera does
not stall the others).

With ``max-latency`` (ms, 0: off) a frame older than that when the mux would take it into a
batch (age = now - its origin timestamp, on the framestamp's clock, ``clock-id``) is dropped
instead, so that a live pipeline that cannot keep up stays real-time rather than falling ever
further behind. Each dropped frame is posted on the bus as an element message
``dcuscope-drop, source=(int), frame=(guint64), reason=(string)late, age-ns=(gint64)``; a batch
left without frames is not pushed.

    gst-launch-1.0 mux name=m batch-size=2 width=640 height=360 ! fakesink \\
        videotestsrc num-buffers=30 ! video/x-raw,format=RGB ! m.sink_0 \\
        videotestsrc num-buffers=30 pattern=ball ! video/x-raw,format=RGB ! m.sink_1
"""

import time
from contextlib import contextmanager
from typing import Iterator

import cv2
import numpy as np

from dcuscope.core.gst import GObject, Gst, GstBase, GstVideo
from dcuscope.plugins.frames import (BATCH_TEMPLATE_CAPS, FrameId, batch_caps, drop_structure, mapped_video, read_frames,
                            write_frames)
from dcuscope.plugins.properties import AttributeProperties

DEFAULT_BATCH_SIZE = 0  # 0: as many as there are sink pads
MIN_PTS_STEP_NS = 1_000_000
"""Least PTS step between batches: one tick of the coarsest container timescale we write (Matroska's 1 ms)."""
DEFAULT_PUSH_TIMEOUT_US = 40000
DEFAULT_WIDTH = 1280
DEFAULT_HEIGHT = 720
DEFAULT_LIVE_SOURCE = False
DEFAULT_MAX_LATENCY_MS = 0  # off
DEFAULT_CLOCK_ID = 0  # CLOCK_REALTIME, the framestamp's default
"""Name of the element message posted for each frame the mux drops."""
LATE = "late"

SINK_CAPS = Gst.Caps.from_string("video/x-raw, format=(string)RGB")


def due_pads(heads: list[tuple[int, int]], period_ns: int, limit: int) -> list[int]:
    """Which streams go into the next batch.

    ``heads``: (running time of the stream's next frame, stream index) for streams that have
    one. The streams whose frame is due within one ``period_ns`` of the earliest, earliest
    first, at most ``limit``.
    """
    if not heads:
        return []
    earliest = min(rt for rt, _ in heads)
    due = sorted((rt, i) for rt, i in heads if period_ns <= 0 or rt < earliest + period_ns)
    return [i for _, i in due[:limit]]


class Mux(AttributeProperties, GstBase.Aggregator):
    __gtype_name__ = "DcuscopeMux"
    __gstmetadata__ = ("Stream muxer", "Video/Muxer", "Batches N video streams into one buffer of N frames",
                       "dcuscope")
    __gsttemplates__ = (
        Gst.PadTemplate.new_with_gtype("sink_%u", Gst.PadDirection.SINK, Gst.PadPresence.REQUEST,
                                       SINK_CAPS, GstBase.AggregatorPad.__gtype__),
        Gst.PadTemplate.new_with_gtype("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                                       BATCH_TEMPLATE_CAPS, GstBase.AggregatorPad.__gtype__),
    )
    __gproperties__ = PROPERTIES = {
        "batch-size": (int, "Batch size", "Most frames in a batch (0: the number of sink pads)",
                       0, 1024, DEFAULT_BATCH_SIZE, GObject.ParamFlags.READWRITE),
        "batched-push-timeout": (int, "Batched push timeout",
                                 "Live sources: microseconds to wait for late cameras before a batch is pushed",
                                 -1, 2**31 - 1, DEFAULT_PUSH_TIMEOUT_US, GObject.ParamFlags.READWRITE),
        "width": (int, "Width", "Width of every frame of the batch", 16, 16384, DEFAULT_WIDTH,
                  GObject.ParamFlags.READWRITE),
        "height": (int, "Height", "Height of every frame of the batch", 16, 16384, DEFAULT_HEIGHT,
                   GObject.ParamFlags.READWRITE),
        "live-source": (bool, "Live source", "The sources are live: push batches on the timeout", DEFAULT_LIVE_SOURCE,
                        GObject.ParamFlags.READWRITE),
        "max-latency": (int, "Max latency",
                        "Drop a frame older than this many milliseconds (now - its origin) instead of batching it "
                        "(0: never)", 0, 2**31 - 1, DEFAULT_MAX_LATENCY_MS, GObject.ParamFlags.READWRITE),
        "clock-id": (int, "Clock id", "Linux clock of the frames' origin timestamps, as the framestamp's clock-id: "
                     "0 realtime, 1 monotonic, 11 tai", 0, 11, DEFAULT_CLOCK_ID, GObject.ParamFlags.READWRITE),
    }

    def __init__(self):
        super().__init__()
        self.init_properties()
        self._infos: dict[str, GstVideo.VideoInfo] = {}
        self._segments: dict[str, Gst.Segment] = {}  # AggregatorPad.segment is not readable from Python
        self._counts: dict[str, int] = {}
        self._caps_sent = False
        self._last_pts: int | None = None
        self._apply_latency()

    def property_changed(self, name):
        if name in ("batched-push-timeout", "live-source"):
            self._apply_latency()

    def _apply_latency(self):
        # The aggregator's own latency is how long it waits for late pads in live mode.
        self.set_property("latency", max(self.batched_push_timeout, 0) * 1000)

    def do_start(self):
        self._caps_sent = False
        self._last_pts = None
        self._counts.clear()
        return True

    def do_sink_event(self, aggpad, event):
        if event.type == Gst.EventType.CAPS:
            self._infos[aggpad.get_name()] = GstVideo.VideoInfo.new_from_caps(event.parse_caps())
        elif event.type == Gst.EventType.SEGMENT:
            self._segments[aggpad.get_name()] = event.parse_segment()
        return GstBase.Aggregator.do_sink_event(self, aggpad, event)

    def do_get_next_time(self):
        """Live: the running time of the earliest frame waiting; the aggregator pushes a batch at this
        time + its latency (``batched-push-timeout`` + the sources' own, which covers a camera's
        capture) without the pads still empty, and waits for a frame while none waits.

        Not the aggregator's ``simple_get_next_time``: that is the position of the output segment,
        which this element does not advance: it stayed 0, every wait had passed before it began,
        and nearly every batch went out with one camera alone (and the thread spun meanwhile)."""
        times = [self._running_time(pad, buf) for pad in self.sinkpads if (buf := pad.peek_buffer()) is not None]
        return min(times) if times else Gst.CLOCK_TIME_NONE

    def _batch_limit(self) -> int:
        return self.batch_size or max(len(self.sinkpads), 1)

    def _period_ns(self) -> int:
        rates = [i.fps_n / i.fps_d for i in self._infos.values() if i.fps_n > 0 and i.fps_d > 0]
        return int(1e9 / max(rates)) if rates else 0

    def _framerate(self) -> tuple[int, int] | None:
        best = max(self._infos.values(), key=lambda i: i.fps_n / i.fps_d if i.fps_d else 0, default=None)
        return (best.fps_n, best.fps_d) if best is not None and best.fps_n > 0 else None

    def do_aggregate(self, timeout):
        pads = list(self.sinkpads)
        heads = []
        for index, pad in enumerate(pads):
            buf = pad.peek_buffer()
            if buf is None:
                continue
            heads.append((self._running_time(pad, buf), index))
        if not heads:
            return Gst.FlowReturn.EOS if all(p.is_eos() for p in pads) else Gst.FlowReturn.OK

        chosen = due_pads(heads, self._period_ns(), self._batch_limit())
        if not self._caps_sent:
            self.set_src_caps(batch_caps(self.width, self.height, self._batch_limit(), self._framerate()))
            self._caps_sent = True

        out = Gst.Buffer.new()
        ids, taken = [], []
        now = time.clock_gettime_ns(self.clock_id) if self.max_latency > 0 else 0
        for index in chosen:
            pad = pads[index]
            buf = pad.pop_buffer()
            frames = read_frames(buf) or [self._own_identity(pad)]
            if self.max_latency > 0 and self._dropped_late(frames, now):
                continue
            out.append_memory(self._frame_memory(pad, buf))
            ids.extend(frames)
            taken.append(index)
        if not taken:
            return Gst.FlowReturn.OK  # every frame was late: no batch
        write_frames(out, ids)
        out.pts = self._stamp(min(rt for rt, i in heads if i in taken))
        out.duration = self._period_ns() or Gst.CLOCK_TIME_NONE
        return self.finish_buffer(out)

    def _dropped_late(self, frames: list[FrameId], now: int) -> bool:
        """Whether the input buffer holding ``frames`` is older than ``max-latency`` (by its oldest
        frame); if so, each of its frames is posted as dropped."""
        age = now - min(f.origin_ns for f in frames)
        if age <= self.max_latency * 1_000_000:
            return False
        for f in frames:
            self.post_message(Gst.Message.new_element(self, drop_structure(f, LATE, now - f.origin_ns)))
        return True

    def _stamp(self, running_time: int) -> int:
        """The batch's PTS: its earliest frame's running time, but at least MIN_PTS_STEP_NS after
        the last batch's. Live, a camera late past the timeout misses its batch; its frame then
        comes out alone, with a running time that batch already had: encoders refuse a PTS that
        does not grow, and containers merge two that fall into one tick of their timescale."""
        if self._last_pts is not None and running_time < self._last_pts + MIN_PTS_STEP_NS:
            running_time = self._last_pts + MIN_PTS_STEP_NS
        self._last_pts = running_time
        return running_time

    def _running_time(self, pad, buf: Gst.Buffer) -> int:
        segment = self._segments.get(pad.get_name())
        if segment is None or buf.pts == Gst.CLOCK_TIME_NONE or segment.format != Gst.Format.TIME:
            return 0
        rt = segment.to_running_time(Gst.Format.TIME, buf.pts)
        return 0 if rt == Gst.CLOCK_TIME_NONE else rt

    def _own_identity(self, pad) -> FrameId:
        # Frames that arrive without identity (no framestamp upstream, e.g. gst-launch): the pad
        # number is the source id and the arrival order the frame number.
        name = pad.get_name()
        count = self._counts.get(name, 0)
        self._counts[name] = count + 1
        return FrameId(int(name.rsplit("_", 1)[1]), count, time.clock_gettime_ns(time.CLOCK_REALTIME))

    def _frame_memory(self, pad, buf: Gst.Buffer) -> Gst.Memory:
        info = self._infos[pad.get_name()]
        packed = info.stride[0] == info.width * 3
        if info.width == self.width and info.height == self.height and packed:
            return buf.peek_memory(0) if buf.n_memory() == 1 else buf.get_all_memory()
        # Not the batch size (or padded rows): scale straight into a new frame memory.
        mem = Gst.Allocator.find(None).alloc(self.width * self.height * 3, None)
        scale_into(buf, info, mem, self.width, self.height)
        return mem


def scale_into(buf: Gst.Buffer, info: GstVideo.VideoInfo, mem: Gst.Memory, width: int, height: int) -> None:
    """Scale the RGB frame in ``buf`` (laid out as ``info``) into ``mem``, a width x height RGB frame."""
    with mapped_video(buf, info) as frame, _mapped_slot(mem, width, height) as target:
        cv2.resize(frame, (width, height), dst=target, interpolation=cv2.INTER_LINEAR)


@contextmanager
def _mapped_slot(mem: Gst.Memory, width: int, height: int) -> Iterator[np.ndarray]:
    """``mem`` mapped for writing as a (height, width, 3) array, unmapped whatever happens."""
    ok, mapinfo = mem.map(Gst.MapFlags.WRITE)
    if not ok:
        raise RuntimeError("mux: cannot map a frame of the batch for writing")
    target = None  # so that a failure below is reported, not masked by the cleanup
    try:
        target = np.frombuffer(mapinfo.data, np.uint8).reshape(height, width, 3)
        yield target
    finally:
        del target
        mem.unmap(mapinfo)


GObject.type_register(Mux)
__gstelementfactory__ = ("mux", Gst.Rank.NONE, Mux)
