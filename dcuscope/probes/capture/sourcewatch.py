"""Drops and source facts of a traced pipeline, written into the tracer's ring as events.

- Drops: an element that drops a frame on purpose (the mux's ``max-latency``) posts an element
  message ``dcuscope-drop`` (``source``, ``frame``, ``reason``) on the bus; it becomes a
  ``drop`` event at the posting element's stage. Taken as a sync message, in the posting
  thread, so no main loop is needed and none is held up.
- Facts, read once a second on the shipping thread from :mod:`dcuscope.pipeline.sourcestats`: each
  source's nominal frame rate (the caps framerate at its framestamp), RTP packets its jitter
  buffer lost, frames its decoder dropped; a fact is written when its value changes.
"""

from __future__ import annotations

import time

import numpy as np

from dcuscope.core.gst import Gst
from dcuscope.pipeline.sourcestats import SourceStats, source_counters
from dcuscope.plugins.frames import DROP_MESSAGE
from dcuscope.protocol.events import (DROP, DROP_REASONS, EVENT_DTYPE, FACT, FACT_DECODER_DROPPED, FACT_LOST_UPSTREAM,
                           FACT_NOMINAL_MHZ)
from dcuscope.probes.capture.tracer import Tracer

POLL_S = 1.0
_REASON_CODES = {name: code for code, name in DROP_REASONS.items()}


class SourceWatch:
    """Writes drop events and source facts of ``tracer``'s pipeline into its ring."""

    def __init__(self, tracer: Tracer, pipeline: Gst.Pipeline) -> None:
        self.tracer, self.pipeline = tracer, pipeline
        self._origin_stage = {e.get_property("source-id"): i for e, i in tracer.stage_elements.items()
                              if e.find_property("source-id") is not None}
        self._stats: SourceStats | None = None
        self._last: dict[tuple[int, int], int] = {}
        self._next_poll = 0.0
        self._bus: Gst.Bus | None = None
        self._handler = 0

    def start(self) -> "SourceWatch":
        self._stats = SourceStats(self.pipeline)
        self._bus = self.pipeline.get_bus()
        self._bus.enable_sync_message_emission()
        self._handler = self._bus.connect("sync-message::element", self._on_element)
        return self

    def stop(self) -> None:
        if self._stats is not None:
            self._stats.close()
            self._stats = None
        if self._bus is not None:
            self._bus.disconnect(self._handler)
            self._bus.disable_sync_message_emission()
            self._bus = None

    def _on_element(self, _bus: Gst.Bus, message: Gst.Message) -> None:
        s = message.get_structure()
        if s is None or s.get_name() != DROP_MESSAGE:
            return
        stage = self.tracer.stage_of(message.src)
        ok_source, source = s.get_int("source")
        ok_frame, frame = s.get_uint64("frame")
        if stage is None or not (ok_source and ok_frame):
            return
        reason = _REASON_CODES.get(s.get_string("reason") or "", 0)
        self.tracer.push(_event(self._now(), frame, source, stage, DROP, reason))

    def poll(self) -> None:
        """Write the facts that changed; at most once per :data:`POLL_S` (shipping thread)."""
        now = time.monotonic()
        if now < self._next_poll:
            return
        self._next_poll = now + POLL_S
        facts = []
        for source, c in source_counters(self.pipeline, self._stats).items():
            stage = self._origin_stage.get(source, 0)
            if c.nominal_fps:
                facts.append((source, stage, FACT_NOMINAL_MHZ, round(c.nominal_fps * 1000)))
            # Both counters are cumulative, and never go back: at the stop rtspsrc takes its
            # jitter buffers out of the pipeline (and the bus watcher is closed) before the
            # shipper's last poll, which would read 0 and have it stand as the run's last word.
            facts += [(source, stage, kind, max(value, self._last.get((source, kind), 0)))
                      for kind, value in ((FACT_LOST_UPSTREAM, c.lost_upstream),
                                          (FACT_DECODER_DROPPED, c.decoder_dropped))]
        changed = [f for f in facts if self._last.get((f[0], f[2])) != f[3]]
        if changed:
            ts = self._now()
            events = np.concatenate([_event(ts, value, source, stage, FACT, kind)
                                     for source, stage, kind, value in changed])
            if self.tracer.push(events):
                self._last.update({(f[0], f[2]): f[3] for f in changed})

    def _now(self) -> int:
        return self.tracer.ring.now(self.tracer.clock_id)


def _event(ts: int, frame: int, source: int, stage: int, point: int, code: int) -> np.ndarray:
    ev = np.zeros(1, EVENT_DTYPE)
    ev[0] = (ts, frame, source, stage, point, code)
    return ev
