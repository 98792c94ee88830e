"""A stage whose delay is known exactly: ``testsleeper`` sleeps on every buffer and records when
each sleep really began and ended, on the probes' clock, with the frames the buffer held.

A measured stage delay is compared with this ground truth of the same run, not with the sleep
asked for: on a loaded machine a sleep wakes up late now and then, which really makes the stage
slower, and both the tracepoints and the element see it.

In process: ``register()``, then ``... ! testsleeper sleep-us=20000 ! ...``; ``element.records``.
Through the CLI: ``python -m tests.probes.sleeper run CONFIG ...`` is ``dcuscope run CONFIG ...``
with the element registered; ``{factory: testsleeper, properties: {sleep-us: N, log: PATH}}``
writes the records to PATH (JSON lines) when the pipeline stops.
"""

from __future__ import annotations

import json
import sys
import time

from core.gst import GObject, Gst, GstBase
from plugins.frames import read_frames

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
        "log": (str, "Log", "JSON-lines file of the records, written when the element stops", "",
                GObject.ParamFlags.READWRITE),
    }

    def __init__(self):
        super().__init__()
        self.sleep_us, self.log = 0, ""
        self.records: list[tuple[list[tuple[int, int]], int, int]] = []
        """Per buffer: its frames [(source, frame)], when the sleep began and ended (CLOCK_REALTIME ns)."""
        self.set_in_place(True)

    def do_get_property(self, prop):
        return self.sleep_us if prop.name == "sleep-us" else self.log

    def do_set_property(self, prop, value):
        if prop.name == "sleep-us":
            self.sleep_us = value
        else:
            self.log = value

    def do_transform_ip(self, buf):
        frames = [(f.source, f.frame) for f in read_frames(buf)]  # before the clock starts: not part of the sleep
        began = time.clock_gettime_ns(time.CLOCK_REALTIME)
        time.sleep(self.sleep_us / 1e6)
        ended = time.clock_gettime_ns(time.CLOCK_REALTIME)
        self.records.append((frames, began, ended))
        return Gst.FlowReturn.OK

    def do_stop(self):
        if self.log:
            with open(self.log, "w") as out:
                for frames, began, ended in self.records:
                    out.write(json.dumps({"frames": frames, "began": began, "ended": ended}) + "\n")
        return True


GObject.type_register(Sleeper)


def register() -> None:
    if Gst.ElementFactory.find("testsleeper") is None:
        Gst.Element.register(None, "testsleeper", Gst.Rank.NONE, Sleeper.__gtype__)


def slept_per_frame(records) -> dict[tuple[int, int], tuple[int, int]]:
    """(source, frame) -> (began, ended) of the sleep on the buffer that held it; ``records`` as
    ``Sleeper.records`` or read back from its log."""
    return {tuple(f): (began, ended) for frames, began, ended in records for f in frames}


def read_log(path) -> list:
    with open(path) as lines:
        return [(r["frames"], r["began"], r["ended"]) for r in map(json.loads, lines)]


if __name__ == "__main__":
    from dcuscope.cli import main

    register()
    sys.exit(main(sys.argv[1:]))
