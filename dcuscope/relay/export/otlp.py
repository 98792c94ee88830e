"""``dcuscope relay --otlp URL``: sampled frames go to an OpenTelemetry backend as traces (OTLP/HTTP, protobuf).

The :class:`~dcuscope.relay.export.otlpsample.Sampler` (an observer of finalised frames, on the event loop)
copies the chosen frames onto a bounded :class:`~dcuscope.relay.export.otlpqueue.FrameQueue`; this exporter's
own thread takes them in batches, builds the spans (:mod:`dcuscope.relay.export.otlpspans`) and posts them with
the SDK's ``OTLPSpanExporter``, each request bounded by ``--otlp-timeout``. The ingest never
waits for it: a full queue drops frames, a failed export drops its frames, both counted
(``dcuscope_otlp_frames_dropped_total{reason}`` in ``/metrics``, ``otlp`` in ``/api/health``).
:meth:`OtlpExporter.stop` sends what is queued while the backend answers (within the timeout)
and ends the thread.

An https endpoint's certificate is checked against ``--otlp-ca`` (:class:`PinnedCA`), else the SDK's
default. A collector that cannot be reached or verified is one log line when exports start failing
(the SDK's own line per attempt is held back, its last kept as the reason) and one when they succeed again.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Iterator

import requests
from opentelemetry.exporter.otlp.proto.http.trace_exporter import OTLPSpanExporter
from opentelemetry.sdk.resources import Resource
from opentelemetry.sdk.trace.export import SpanExportResult
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from dcuscope.relay.export.metrics import RelayCollector
from dcuscope.relay.export.otlpconfig import OtlpConfig
from dcuscope.relay.export.otlpframes import FrameBatch
from dcuscope.relay.export.otlpqueue import FrameQueue, OtlpCounters
from dcuscope.relay.export.otlpsample import Sampler
from dcuscope.relay.export.otlpspans import node_resource, spans_of
from dcuscope.relay.live.state import RelayState

EXPORT_FRAMES = 128
"""Frames per export request at most (~20 spans each with 5 stages: ~0.5 MB of protobuf)."""
LINGER_S = 1.0
"""How long a request waits for more frames before it goes with fewer."""
MAX_BUSY = 0.03
"""Share of one core's time the exporter may spend building, encoding and posting spans (~30-40 us
a span, mostly the SDK's encoder): past it, it rests, the queue fills and frames are dropped
(``queue_full``), so that the ingest keeps at least 97 % of the interpreter (py-spy on a saturated relay: at
5 % the exporter thread took 4 % of its samples, with the scrapes' windows ~8 % in all)."""
MAX_REST_S = 5.0

log = logging.getLogger(__name__)
SDK_LOG = logging.getLogger(OTLPSpanExporter.__module__)
"""Where the SDK's exporter logs each failed attempt (a line per retry)."""


class PinnedCA(requests.Session):
    """A session whose ``verify`` (``--otlp-ca``) the environment cannot replace: requests lets
    ``REQUESTS_CA_BUNDLE`` or ``CURL_CA_BUNDLE`` win over a session's own (psf/requests#3829)."""

    def merge_environment_settings(self, url, proxies, stream, verify, cert):
        settings = super().merge_environment_settings(url, proxies, stream, verify, cert)
        settings["verify"] = self.verify
        return settings


class _FirstReason(logging.Filter):
    """Holds back the SDK's lines of a failed export, keeping the first (the cause; the last says only
    that the retries ran out) as its reason."""

    def __init__(self) -> None:
        super().__init__()
        self.first = ""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            self.first = self.first or record.getMessage()[:400]
            return False
        return True


class OtlpExporter:
    def __init__(self, config: OtlpConfig, state: RelayState) -> None:
        self.config = config
        self.counters = OtlpCounters()
        self.queue = FrameQueue(config.queue)
        self.sampler = Sampler(state, config.every, self.queue, self.counters)
        self._exporter = OTLPSpanExporter(endpoint=config.url, timeout=config.timeout_s, certificate_file=config.ca,
                                          session=PinnedCA() if config.ca else None)
        self._reason = _FirstReason()
        SDK_LOG.addFilter(self._reason)
        self._resources: dict[str, Resource] = {}
        self._thread = threading.Thread(target=self._run, name="dcuscope-otlp", daemon=True)
        self._failing = False
        self._stop_by: float | None = None
        self._wake = threading.Event()
        self._state = state

    def attach(self, metrics: RelayCollector) -> None:
        """Be told of every finalised frame, and show in ``/metrics``."""
        self._state.observers.append(self.sampler)
        metrics.extra.append(self.metric_families)
        metrics.queues["otlp"] = lambda: self.queue.frames

    def start(self) -> None:
        self._thread.start()

    async def stop(self) -> None:
        """Send what is queued while exports succeed, for at most the timeout; then end the thread."""
        self._stop_by = time.monotonic() + self.config.timeout_s
        self.queue.close()
        self._wake.set()
        if self._thread.is_alive():
            # An export in flight when the time is up ends by its own timeout; the thread is a daemon.
            await asyncio.to_thread(self._thread.join, 2 * self.config.timeout_s + 1)
        self._exporter.shutdown()
        SDK_LOG.removeFilter(self._reason)

    def _run(self) -> None:
        while batches := self.queue.take(EXPORT_FRAMES, LINGER_S):
            if self._stop_by is not None and (self._failing or time.monotonic() > self._stop_by):
                self.counters.dropped["export_failed"] += sum(map(len, batches)) + self.queue.clear()
                return
            cpu = self._export(batches)
            if self._stop_by is None:
                # CPU time, not wall: a slow backend costs waiting, not the ingest's interpreter.
                self._wake.wait(min(cpu * (1 / MAX_BUSY - 1), MAX_REST_S))

    def _export(self, batches: list[FrameBatch]) -> float:
        """Send ``batches``; returns the CPU time it took."""
        t0, cpu0 = time.perf_counter(), time.thread_time()
        frames = sum(map(len, batches))
        spans = []
        self._reason.first = ""
        try:
            for batch in batches:
                spans += spans_of(batch, self._resource(batch.node))
            ok = self._exporter.export(spans) is SpanExportResult.SUCCESS
        except Exception:  # noqa: BLE001 - the exporter's fault loses its frames, never the relay
            log.exception("OTLP export of %d frames failed", frames)
            ok = False
        c = self.counters
        c.exports += 1
        if ok:
            c.frames_exported += frames
            c.spans_exported += len(spans)
        else:
            c.dropped["export_failed"] += frames
        if ok == self._failing:
            if ok:
                log.warning("OTLP export to %s works again", self.config.url)
            else:
                log.warning("OTLP export to %s failing (%s); its frames are dropped and counted "
                            "(dcuscope_otlp_frames_dropped_total) until one succeeds", self.config.url,
                            self._reason.first or "no reason given")
        self._failing = not ok
        cpu = time.thread_time() - cpu0
        c.export_seconds += time.perf_counter() - t0
        c.cpu_seconds += cpu
        c.most_cpu_seconds = max(c.most_cpu_seconds, cpu)
        return cpu

    def _resource(self, node: str) -> Resource:
        if node not in self._resources:
            self._resources[node] = node_resource(node)
        return self._resources[node]

    def view(self) -> dict:
        """The counters, for /api/health."""
        c = self.counters
        return {"url": self.config.url, "every": self.config.every, "frames": dict(c.frames),
                "dropped": dict(c.dropped), "frames_exported": c.frames_exported, "spans_exported": c.spans_exported,
                "exports": c.exports, "export_seconds": c.export_seconds, "cpu_seconds": c.cpu_seconds,
                "queue_frames": self.queue.frames, "queue_capacity_frames": self.queue.capacity}

    def metric_families(self) -> Iterator[Metric]:
        """The exporter's figures in Prometheus' terms (``relay.export.metrics.RelayCollector.extra``)."""
        c = self.counters
        frames = CounterMetricFamily("dcuscope_otlp_frames", "Frames queued for OTLP export, by why they were chosen "
                                     "(over_limit: over the node's --frame-limit; sampled: 1 in --otlp-every)",
                                     labels=["why"])
        for why, n in c.frames.items():
            frames.add_metric([why], n)
        dropped = CounterMetricFamily("dcuscope_otlp_frames_dropped", "Frames chosen for OTLP export but not exported, "
                                      "by reason", labels=["reason"])
        for reason, n in c.dropped.items():
            dropped.add_metric([reason], n)
        yield frames
        yield dropped
        yield CounterMetricFamily("dcuscope_otlp_spans_exported", "Spans the OTLP backend accepted",
                                  value=c.spans_exported)
        yield GaugeMetricFamily("dcuscope_otlp_queue_frames", "Frames waiting for OTLP export", value=self.queue.frames)
        yield GaugeMetricFamily("dcuscope_otlp_queue_capacity_frames", "Frames the OTLP export queue holds at most "
                                "(--otlp-queue)", value=self.queue.capacity)
