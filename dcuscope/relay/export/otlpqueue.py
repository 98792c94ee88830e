"""The bounded queue between the OTLP sampler (event loop) and the exporter's thread, and its counters.

The sampler only ever puts (never waits: what does not fit is dropped and counted); the exporter
thread takes batches of frames, waiting a little for a batch to fill so that a low rate of frames
still goes out in few requests.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

from dcuscope.relay.export.otlpframes import FrameBatch

WHY = ("sampled", "over_limit")
DROP_REASONS = ("queue_full", "export_failed")


@dataclass
class OtlpCounters:
    """Each figure is written by one thread only (frames and queue_full: the event loop; the rest:
    the exporter), so plain ints need no lock."""
    frames: dict[str, int] = field(default_factory=lambda: dict.fromkeys(WHY, 0))
    """Frames queued for export, by why they were chosen (over the limit wins over the 1-in-N sample)."""
    dropped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(DROP_REASONS, 0))
    """Frames not exported, by reason."""
    frames_exported: int = 0
    spans_exported: int = 0
    exports: int = 0
    """Export requests made (successful or not)."""
    export_seconds: float = 0.0
    """Wall time the exporter spent building and sending spans."""
    cpu_seconds: float = 0.0
    """CPU time its thread spent on it: what it takes from the ingest's interpreter."""
    most_cpu_seconds: float = 0.0
    """The most CPU time one export took."""


class FrameQueue:
    """At most ``capacity`` frames, in the order they were put, as :class:`FrameBatch` chunks."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._chunks: deque[FrameBatch] = deque()
        self._frames = 0
        self._closed = False
        self._cond = threading.Condition()

    @property
    def frames(self) -> int:
        return self._frames

    def room(self) -> int:
        """Frames that fit now. With one producer it only grows until that producer puts."""
        return self.capacity - self._frames

    def put(self, batch: FrameBatch) -> None:
        """Append ``batch`` (the caller cut it to :meth:`room`)."""
        with self._cond:
            self._chunks.append(batch)
            self._frames += len(batch)
            self._cond.notify()

    def take(self, most: int, linger_s: float) -> list[FrameBatch]:
        """Up to ``most`` frames: waits for a first one, then up to ``linger_s`` for more (not once
        closed); empty only when closed and drained."""
        with self._cond:
            self._cond.wait_for(lambda: self._frames or self._closed)
            deadline = time.monotonic() + linger_s
            while self._frames < most and not self._closed and (left := deadline - time.monotonic()) > 0:
                self._cond.wait(left)
            out, n = [], 0
            while self._chunks and n < most:
                head, rest = self._chunks[0].split(most - n)
                out.append(head)
                n += len(head)
                if len(rest):
                    self._chunks[0] = rest
                else:
                    self._chunks.popleft()
            self._frames -= n
            return out

    def close(self) -> None:
        """Wake the taker for good: what is left is taken without lingering."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def clear(self) -> int:
        """Forget every frame queued; returns how many."""
        with self._cond:
            n, self._frames = self._frames, 0
            self._chunks.clear()
            return n
