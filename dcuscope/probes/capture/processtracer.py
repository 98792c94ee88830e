"""The dcuscope GStreamer tracer made from Python, as ``GST_TRACERS=dcuscope(...)`` would make it:
every element of every pipeline that runs from now on traced from hooks alone, frames given
their identity where video starts, the trace file written by the tracer's own C thread
(probes/capture/c/tracer.c). ``dcuscope run`` uses it for ``launch:`` configs, whose elements carry no
framestamp; followed by :class:`dcuscope.probes.ship.tailship.TailShipper` for a relay.

    tracer = ProcessTracer(node="DCU-1", trace=Path("dcu1.trace.jsonl"), clock="realtime")
    ... run the pipeline ...
    stages, events, dropped = tracer.finish()   # drains, writes the end line; the hooks stay, idle
"""

from __future__ import annotations

import ctypes
import json
import os
from pathlib import Path

from dcuscope.probes.capture.native import BuildError, load, unavailable_reason
from dcuscope.probes.trace.errors import TraceError
from dcuscope.probes.trace.tracefile import _parse_header


def tracer_params(node: str, trace: Path, clock: str = "realtime", capacity: int | None = None) -> str:
    """The tracer's parameter text, quoted as GstStructure wants it."""
    def quoted(text: str) -> str:
        return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'

    params = f"node={quoted(node)},trace={quoted(str(trace))},clock={clock}"
    return params + (f",capacity={capacity}" if capacity else "")


class ProcessTracer:
    def __init__(self, node: str, trace: Path, clock: str = "realtime", capacity: int | None = None):
        self._lib = load()
        if self._lib is None:
            raise BuildError(f"the dcuscope tracer needs the native library: {unavailable_reason()}")
        self.trace = Path(trace)
        self._tracer = self._lib.dcu_tracer_new(tracer_params(node, self.trace, clock, capacity).encode())
        if not self._tracer:
            raise TraceError(f"{self.trace}: cannot write the trace file")

    def finish(self) -> tuple[int, int, int]:
        """Close the trace; returns its (stages, events, dropped), read from its first and last
        lines (the header and the end line), not from the whole file."""
        if self._tracer:
            self._lib.dcu_tracer_finish(ctypes.c_void_p(self._tracer))
            self._tracer = None
        try:
            with open(self.trace, "rb") as f:
                header = _parse_header(self.trace, f.readline())
                f.seek(max(0, f.seek(0, os.SEEK_END) - 256))
                end = json.loads(f.read().rstrip(b"\n").rsplit(b"\n", 1)[-1])["end"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise TraceError(f"{self.trace}: the tracer did not close its trace ({exc})") from exc
        return len(header.stages), int(end["events"]), int(end["dropped"])
