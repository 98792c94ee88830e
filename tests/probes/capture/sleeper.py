"""A stage whose delay is known exactly: ``testsleeper`` sleeps on every buffer and records when
each sleep really began and ended, on the probes' clock, with the frames the buffer held.

A measured stage delay is compared with this ground truth of the same run, not with the sleep
asked for: on a loaded machine a sleep wakes up late now and then, which really makes the stage
slower, and both the tracepoints and the element see it.

``register()``, then ``... ! testsleeper sleep-us=20000 ! ...``; ``element.records``. In process
only: where the pipeline runs in a process of its own (``dcuscope run``), GStreamer's own latency
tracer gives the same ground truth (tests/probes/capture/test_pipeline_probes.py).
"""

from __future__ import annotations

import time

from dcuscope.core.gst import GObject, Gst, GstBase
from dcuscope.plugins.frames import read_frames

CAPS = Gst.Caps.new_any()


class Sleeper(GstBase.BaseTransform):
    __gtype_name__ = "DcuscopeTestSleeper"
    __gstmetadata__ = ("Test sleeper", "Filter", "Sleeps on every buffer and records the sleeps", "dcuscope tests")
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, CAPS),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, CAPS),
    )
    __gproperties__ = {
        "sleep-us": (int, "Sleep", "Microseconds to sleep on each buffer", 0, 10_000_000, 0,
                     GObject.ParamFlags.READWRITE),
    }

    def __init__(self):
        super().__init__()
        self.sleep_us = 0
        self.records: list[tuple[list[tuple[int, int]], int, int]] = []
        """Per buffer: its frames [(source, frame)], when the sleep began and ended (CLOCK_REALTIME ns)."""
        self.set_in_place(True)

    def do_get_property(self, prop):
        return self.sleep_us

    def do_set_property(self, prop, value):
        self.sleep_us = value

    def do_transform_ip(self, buf):
        frames = [(f.source, f.frame) for f in read_frames(buf)]  # before the clock starts: not part of the sleep
        began = time.clock_gettime_ns(time.CLOCK_REALTIME)
        time.sleep(self.sleep_us / 1e6)
        ended = time.clock_gettime_ns(time.CLOCK_REALTIME)
        self.records.append((frames, began, ended))
        return Gst.FlowReturn.OK


GObject.type_register(Sleeper)


def register() -> None:
    if Gst.ElementFactory.find("testsleeper") is None:
        Gst.Element.register(None, "testsleeper", Gst.Rank.NONE, Sleeper.__gtype__)


def slept_per_frame(records) -> dict[tuple[int, int], tuple[int, int]]:
    """(source, frame) -> (began, ended) of the sleep on the buffer that held it (``Sleeper.records``)."""
    return {tuple(f): (began, ended) for frames, began, ended in records for f in frames}
