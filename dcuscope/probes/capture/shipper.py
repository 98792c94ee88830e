"""The shipping thread: drains a tracer's ring in batches and hands them to exporters.

    shipper = Shipper(tracer, [TraceFileWriter("run.trace")]).start()
    ... run the pipeline ...
    shipper.stop()        # final drain, then exporter.close(dropped)

Probes only timestamp and enqueue; this thread does everything else, so a slow exporter costs
ring space (and, when the ring fills, counted drops), never streaming-thread time. Every
exporter call happens on this thread (see :class:`dcuscope.protocol.events.Exporter`). An exporter that
raises is reported once, through the ``dcuscope.probes`` logger and :attr:`Shipper.errors`,
and disabled; the others, and the pipeline, carry on.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable, Sequence

from dcuscope.probes.capture.tracer import Tracer
from dcuscope.protocol.events import EXPORTER_CLOSE_S, Exporter

log = logging.getLogger("dcuscope.probes")

DEFAULT_INTERVAL_S = 0.02
"""How often the ring is drained: an event reaches the exporters within this (the relay's live lag)."""
FACTS_INTERVAL_S = 0.1
"""How often ``before_ship`` (the sources' counters) is called, at most."""
DEFAULT_BATCH = 1 << 16
STOP_MARGIN_S = 5.0
"""What ``stop`` waits beyond the exporters' close: the final drain."""


def close_timeout_s(exporters: Sequence[Exporter]) -> float:
    """The longest the exporters' ``close`` may take (``EXPORTER_CLOSE_S`` unless one says)."""
    return max((float(getattr(e, "close_timeout_s", EXPORTER_CLOSE_S)) for e in exporters), default=0.0)


class Shipper:
    """Background daemon thread moving events from ``tracer`` to ``exporters``."""

    def __init__(self, tracer: Tracer, exporters: Sequence[Exporter], interval_s: float = DEFAULT_INTERVAL_S,
                 batch: int = DEFAULT_BATCH, before_ship: Callable[[], None] | None = None):
        if interval_s <= 0:
            raise ValueError(f"interval_s must be > 0, got {interval_s}")
        self.tracer = tracer
        self.exporters = list(exporters)
        self.interval_s = interval_s
        self.batch = batch
        self.shipped = 0
        """Events handed to the exporters so far."""
        self.errors: list[str] = []
        """One line per exporter that failed and was disabled."""
        self._active = list(self.exporters)
        self._before_ship = before_ship
        """Called on this thread before a drain, at most every FACTS_INTERVAL_S (probes.capture.sourcewatch adds
        its facts there)."""
        self._facts_at = float("-inf")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dcuscope-shipper", daemon=True)

    def start(self) -> "Shipper":
        self._thread.start()
        return self

    def stop(self, timeout: float | None = None) -> None:
        """Ship what is left, close the exporters and end the thread (by default waiting as long as
        the slowest exporter's close may take, plus STOP_MARGIN_S)."""
        if timeout is None:
            timeout = close_timeout_s(self.exporters) + STOP_MARGIN_S
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def __enter__(self) -> "Shipper":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _run(self) -> None:
        self._each("start", self.tracer.header)
        while not self._stop.wait(self.interval_s):
            self._ship()
        self._ship(final=True)
        self._each("close", self.tracer.dropped)

    def _ship(self, final: bool = False) -> None:
        now = time.monotonic()
        if self._before_ship is not None and (final or now - self._facts_at >= FACTS_INTERVAL_S):
            self._facts_at = now
            try:
                self._before_ship()
            except Exception as exc:  # noqa: BLE001 - facts are extras: never stop the shipping for them
                log.error("dcuscope: reading source counters failed: %s", exc)
                self._before_ship = None
        while True:
            try:
                events = self.tracer.drain(self.batch)
            except Exception as exc:  # noqa: BLE001 - the thread must outlive a bad drain
                log.error("dcuscope: draining probe events failed: %s", exc)
                return
            if len(events) == 0:
                return
            self._each("write", events)
            self.shipped += len(events)
            if len(events) < self.batch:
                return

    def _each(self, method: str, arg) -> None:
        for exporter in list(self._active):
            try:
                getattr(exporter, method)(arg)
            except Exception as exc:  # noqa: BLE001 - an exporter must not kill the run
                message = f"exporter {type(exporter).__name__} failed in {method}() and is disabled: {exc}"
                log.error("dcuscope: %s", message)
                self.errors.append(message)
                self._active.remove(exporter)
