"""The pure-Python event ring and its pad probes: the fallback when the native library is missing.

Same interface as :class:`dcuscope.probes.capture.native.NativeRing` (``attach``, ``detach``, ``drain``,
``stats``, ``now``, ``close``, ``capacity``, ``backend``). A Python pad probe costs 15-60 µs
(PyGObject marshalling, GIL), so this is the slow path; it does the least it can per buffer:
one clock read, one meta lookup, one ``deque.append`` of a tuple. ``deque.append`` and
``popleft`` are atomic under the GIL, so producers never lock; counters that producers bump
are deques of ints too (appending is atomic, ``+=`` on a shared int is not), summed by the
consumer.

Unlike the native probes, a Python probe cannot tell whether a sink pad's element handles
buffer lists itself: where it does not, GStreamer splits the list and probes each buffer
again, so such a pad records the frames of a list twice (the statistics keep the first).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from dcuscope.core.gst import Gst
from dcuscope.plugins.frames import FRAMES_CAPS
from dcuscope.protocol.events import EVENT_DTYPE

DEFAULT_CAPACITY = 1 << 16


@dataclass(frozen=True)
class RingStats:
    written: int
    """Events accepted into the ring since it was made (drained or not)."""
    dropped: int
    """Events lost because the ring was full."""
    unidentified: int
    """Buffers that passed a tracepoint without frame identity (no event recorded)."""


class PythonRing:
    """A bounded multi-producer, single-consumer event buffer fed by Python pad probes.

    The bound is checked without a lock, so concurrent producers may overshoot it by at most
    one buffer each; it never blocks.
    """

    backend = "python"

    def __init__(self, capacity: int = DEFAULT_CAPACITY):
        self.capacity = max(int(capacity), 1)
        self._events: deque = deque()
        self._drops: deque = deque()
        self._unidentified: deque = deque()
        self._drained = 0
        self._dropped = 0
        self._unidentified_total = 0
        self._consumer = threading.Lock()  # serialises consumers only; probes never take it

    def attach(self, pad: Gst.Pad, stage: int, point: int, clock_id: int) -> int:
        """Add a tracepoint on ``pad``; returns a handle for :meth:`detach`."""
        probe_id = pad.add_probe(Gst.PadProbeType.BUFFER | Gst.PadProbeType.BUFFER_LIST,
                                 self._make_probe(stage, point, clock_id))
        if not probe_id:
            raise ValueError(f"cannot add a probe on {pad}")
        return int(probe_id)

    def detach(self, pad: Gst.Pad, handle: int) -> None:
        pad.remove_probe(handle)

    def _make_probe(self, stage: int, point: int, clock_id: int):
        # Everything the probe touches is bound to a local: no attribute lookups per buffer.
        events, drops, unidentified, cap = self._events, self._drops, self._unidentified, self.capacity
        now, frames_caps = time.clock_gettime_ns, FRAMES_CAPS
        BUFFER, OK = Gst.PadProbeType.BUFFER, Gst.PadProbeReturn.OK

        def record(buf: Gst.Buffer, ts: int) -> None:
            meta = buf.get_reference_timestamp_meta(frames_caps)
            if meta is None:
                unidentified.append(1)
                return
            try:
                s = meta.reference[0]
                sources, frames = s.get_value("source"), s.get_value("frame")
                if isinstance(sources, int):
                    sources, frames = (sources,), (frames,)
                n = min(len(sources), len(frames))
            except (TypeError, AttributeError):
                n = 0
            if n == 0:
                unidentified.append(1)
            elif len(events) + n > cap:
                drops.append(n)
            elif n == 1:
                events.append((ts, frames[0], sources[0], stage, point, 0))
            else:
                events.extend([(ts, f, s, stage, point, 0) for s, f in zip(sources, frames)])

        def probe(pad: Gst.Pad, info: Gst.PadProbeInfo) -> Gst.PadProbeReturn:
            ts = now(clock_id)
            if info.type & BUFFER:
                record(info.get_buffer(), ts)
            else:
                buffers = info.get_buffer_list()
                for i in range(buffers.length()):
                    record(buffers.get(i), ts)
            return OK

        return probe

    def push(self, events: np.ndarray) -> int:
        """Append events made elsewhere (drops, facts); returns how many went in (0 or all)."""
        if len(self._events) + len(events) > self.capacity:
            self._drops.append(len(events))
            return 0
        self._events.extend(tuple(int(v) for v in e) for e in events.tolist())
        return len(events)

    def drain(self, max_events: int | None = None) -> np.ndarray:
        """Events recorded since the last drain (oldest first), as EVENT_DTYPE."""
        with self._consumer:
            n = len(self._events) if max_events is None else min(max_events, len(self._events))
            popleft = self._events.popleft
            rows = [popleft() for _ in range(n)]
            self._drained += n
        return np.array(rows, EVENT_DTYPE) if rows else np.empty(0, EVENT_DTYPE)

    def stats(self) -> RingStats:
        with self._consumer:
            self._dropped += _sum_out(self._drops)
            self._unidentified_total += _sum_out(self._unidentified)
            return RingStats(self._drained + len(self._events), self._dropped, self._unidentified_total)

    def now(self, clock_id: int) -> int:
        return time.clock_gettime_ns(clock_id)

    def close(self) -> None:
        pass


def _sum_out(counts: deque) -> int:
    total = 0
    for _ in range(len(counts)):
        total += counts.popleft()
    return total
