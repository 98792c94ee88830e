"""Stopping a live run at once, without draining its backlog.

A file waits for the pipeline; a camera does not. A live pipeline that cannot keep up builds a
backlog in front of its slowest stage (the mux's inputs, queues) and before its frame stamps
(rtspsrc's jitter buffer, the decoder), and an end-of-stream sent into the sources comes out
only behind all of it: a run told to stop drains for as long as it lags, without bound. A live
stop instead:

- ends every source at its frame stamp (:meth:`dcuscope.pipeline.sources.SourceBin.end_now`): frames not
  stamped yet are discarded without ever getting an identity, and end-of-stream follows the
  last frame the source stamped;
- discards the frames still waiting in the stages that queue them (the mux, which is an
  aggregator, and queue stages) as they come out, each posted as dropped (``dcuscope-drop``,
  reason ``stopped``, as the mux posts a late frame), so that the trace counts every frame;
- lets the work under way finish: a batch inside a stage when the stop came reaches the sink.

End-of-stream then reaches the sink within about one batch's service time, and an MP4 is
finalised.
"""

from __future__ import annotations

import time
from typing import Iterable

from dcuscope.core.gst import Gst, GstBase
from dcuscope.plugins.frames import drop_structure, read_frames

STOPPED = "stopped"
"""Reason of the frames a live stop discards (``protocol.events.DROP_REASONS``)."""
QUEUE_FACTORIES = ("queue", "queue2", "multiqueue")
"""Elements that hold frames in a queue of their own, pushed out by a thread of their own."""


def holds_backlog(element: Gst.Element) -> bool:
    """Whether frames wait inside ``element``: an aggregator (the mux) or a queue."""
    factory = element.get_factory()
    return isinstance(element, GstBase.Aggregator) or (factory is not None and factory.get_name() in QUEUE_FACTORIES)


class LiveStop:
    """Stop a live pipeline now: sources end at their stamps, queued frames are dropped, counted."""

    def __init__(self, stages: Iterable[Gst.Element], sources: Iterable, clock_id: int):
        self.stages = [s for s in stages if holds_backlog(s)]
        self.sources = list(sources)
        self.clock_id = clock_id
        self._dropped: list[int] = []  # one slot per probed pad, each written by that pad's thread only

    def start(self) -> None:
        for element in self.stages:
            for pad in element.srcpads:
                self._dropped.append(0)
                pad.add_probe(Gst.PadProbeType.BUFFER | Gst.PadProbeType.BUFFER_LIST,
                              self._discard, element, len(self._dropped) - 1)
        for source in self.sources:
            source.end_now()

    @property
    def dropped(self) -> int:
        """Frames discarded so far (those a batch held counted one by one)."""
        return sum(self._dropped)

    def _discard(self, _pad: Gst.Pad, info: Gst.PadProbeInfo, element: Gst.Element, slot: int):
        buffers = info.get_buffer_list() if info.type & Gst.PadProbeType.BUFFER_LIST else None
        buffers = [buffers.get(i) for i in range(buffers.length())] if buffers is not None else [info.get_buffer()]
        now = time.clock_gettime_ns(self.clock_id)
        for buf in buffers:
            for frame in read_frames(buf):
                element.post_message(Gst.Message.new_element(element, drop_structure(frame, STOPPED,
                                                                                     now - frame.origin_ns)))
                self._dropped[slot] += 1
        return Gst.PadProbeReturn.DROP
