"""``GET /metrics``: the relay in the Prometheus text exposition format (``prometheus_client``).

:class:`RelayCollector` builds every family at scrape time from the relay's state, in its own
``CollectorRegistry`` per relay (never the process-wide one): the per-frame histograms
(:mod:`dcuscope.relay.export.framemetrics`), the per-node gauges and counters (:mod:`dcuscope.relay.export.nodemetrics`) and the
relay's own figures (events and batches ingested, queue depths, connections, live bytes).
Exporters add theirs through :attr:`RelayCollector.extra`. The text is what
``generate_latest(collector.registry)`` writes, its histograms written in bulk
(:mod:`dcuscope.relay.export.exposition`). The route is READ in :mod:`dcuscope.relay.guard.policy`, as ``/api`` is
(``Authorization: Bearer TOKEN``: the admin's or a viewer's).

Every per-node series is labelled ``node`` (its newest run only); no label holds a frame
number, and only ``dcuscope_node_info`` a run id. A relay shows the figures of the runs it holds
(``RelayState.holds``: on a shared PostgreSQL store, those streaming to it), so that relays sharing a
store never count one run's frames or events twice; of a run it keeps in memory without holding it
(its connection ended: another relay may take it) it shows only the node's state
(``nodemetrics.STATE``). The shipped rules (configs/prometheus/) aggregate every node across
relays on that ground.

Series per node, at most, with S stages (``--limit stages``, 64), K sources (``--limit sources``,
256), G = min(gap pairs, framemetrics.MAX_GAPS + 1) and R = len(protocol.events.DROP_REASONS) (6),
each histogram series being len(BUCKETS_S) + 3 = 34 samples (buckets, +Inf, sum, count)::

    34 (2 + 3 S + G)  +  4 S  +  K (6 + R)  +  18

(~1,250 for a typical node: 8 stages, 8 gaps, 4 sources; 14,328 at every default
limit), plus 12 for the relay itself, one per refusal reason (``dcuscope_relay_refused_total``) and those
of :attr:`RelayCollector.extra`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

import numpy as np
from aiohttp import web
from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.utils import floatToGoString
from prometheus_client.registry import Collector

from dcuscope.relay.export.exposition import exposition
from dcuscope.relay.export.framemetrics import FrameMetrics
from dcuscope.relay.export.hopmetrics import HopMetrics
from dcuscope.relay.export.nodemetrics import NodeMetrics
from dcuscope.relay.guard.connections import ConnGuard
from dcuscope.relay.guard.policy import add_read
from dcuscope.relay.ingest.endpoint import Ingest
from dcuscope.relay.live.state import RelayState

BUCKETS_S = tuple(float(f"{m}e{e}") for e in range(-4, 1) for m in (1, 1.5, 2, 3, 5, 7)) + (10.0,)
"""Upper bounds of every histogram's buckets, s: 1-1.5-2-3-5-7 per decade, 0.1 ms to 10 s (then +Inf)."""
METRICS_PATH = "/metrics"


class RelayCollector(Collector):
    """Every family of ``/metrics``, built from the relay's state when scraped."""

    def __init__(self, state: RelayState, ingest: Ingest, guard: ConnGuard,
                 refusals: Callable[[], dict[str, int]] = dict) -> None:
        self.state, self.ingest, self.guard, self.refusals = state, ingest, guard, refusals
        self.frames = FrameMetrics(state, BUCKETS_S)
        self.hops = HopMetrics(np.array([round(b * 1e9) for b in BUCKETS_S], np.int64),
                               [floatToGoString(b) for b in BUCKETS_S] + ["+Inf"])
        state.observers.append(self.frames.observe)
        self.nodes = NodeMetrics(state)
        self.extra: list[Callable[[], Iterable[Metric]]] = []
        """More families, asked for at each scrape (the OTLP exporter's counters)."""
        self.queues: dict[str, Callable[[], float]] = {}
        """More queue depths, as ``dcuscope_relay_queue_depth{queue=NAME}`` (the OTLP exporter's)."""
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(self)

    def collect(self) -> Iterator[Metric]:
        # The window's statistics first: computing them may finalise frames the histograms then count.
        yield from self.nodes.families()
        yield from self.frames.families()
        yield from self._journey_families()
        yield from self._relay_families()
        for more in self.extra:
            yield from more()

    def _journey_families(self) -> Iterator[Metric]:
        """Frames that went from one DCU's pipeline to another's (:mod:`dcuscope.relay.export.hopmetrics`)."""
        self.hops.update(self.state.joined())
        yield from self.hops.families()

    def _relay_families(self) -> Iterator[Metric]:
        state, ingest = self.state, self.ingest
        yield CounterMetricFamily("dcuscope_relay_events", "Events ingested (stored and fed to the live state)",
                                  value=ingest.events_in)
        yield CounterMetricFamily("dcuscope_relay_batches", "Batches ingested (stored and fed to the live state)",
                                  value=ingest.batches_in)
        depth = GaugeMetricFamily("dcuscope_relay_queue_depth", "Items waiting: storage writes and calls "
                                  "(storage), events not yet merged into live states (live_pending), frames waiting for "
                                  "OTLP export (otlp)", labels=["queue"])
        depth.add_metric(["storage"], state.storage.queued)
        depth.add_metric(["live_pending"], sum(rs.live.pending_events for rs in state.runs.values()))
        for name, depth_of in self.queues.items():
            depth.add_metric([name], depth_of())
        yield depth
        conns = GaugeMetricFamily("dcuscope_relay_connections", "Connections held: ingest WebSockets, TCP in all",
                                  labels=["kind"])
        conns.add_metric(["ingest"], ingest.connected)
        conns.add_metric(["tcp"], self.guard.open)
        yield conns
        yield from self._store_families()
        yield GaugeMetricFamily("dcuscope_relay_live_bytes", "Bytes the runs' live states hold",
                                value=state.memory_view()["live_bytes"])
        # One family: the guards' refusals (connections, requests) and the relay's (hellos, credentials,
        # roles, names) share their counter where they overlap.
        refused = CounterMetricFamily("dcuscope_relay_refused", "Connections, requests and hellos refused, by reason "
                                      "(as /api/health's refused: credentials, roles, limits, names)", labels=["reason"])
        for reason, count in sorted({**self.guard.refused, **self.refusals()}.items()):
            refused.add_metric([reason], count)
        yield refused

    def _store_families(self) -> Iterator[Metric]:
        storage = self.state.storage
        yield GaugeMetricFamily("dcuscope_relay_store_up", "1 while the store takes writes, 0 while they fail "
                                "(as /api/health's storage.ok)", value=int(storage.health()["ok"]))
        yield GaugeMetricFamily("dcuscope_relay_store_waiting_for_standby", "1 while the store's commits wait for "
                                "its synchronous standby (writes held back), else 0", value=int(storage.waiting))
        yield CounterMetricFamily("dcuscope_relay_store_commits", "Transactions that committed batches (a round's "
                                  "batches, of every node, commit in one)", value=storage.commits)
        yield CounterMetricFamily("dcuscope_relay_store_batches", "Batches those transactions stored",
                                  value=storage.batches_written)
        yield CounterMetricFamily("dcuscope_relay_store_failed_writes", "Writes refused for the store failing "
                                  "(their nodes send them again)", value=storage.failed_writes)
        timeouts = CounterMetricFamily("dcuscope_relay_store_timeouts", "Writes cancelled for taking longer than "
                                       "--store-timeout, by cause (synchronous_standby: committed on the primary, "
                                       "not confirmed by its synchronous standby)", labels=["cause"])
        for cause, count in sorted(storage.timeouts.items()):
            timeouts.add_metric([cause], count)
        yield timeouts

    def exposition(self) -> bytes:
        """The text format of every family now (what ``generate_latest(self.registry)`` writes, faster)."""
        return exposition(self.collect())


def add_metrics_route(app: web.Application, collector: RelayCollector) -> None:
    """``GET /metrics``, for READ principals as ``/api`` is."""

    async def metrics(request: web.Request) -> web.Response:
        return web.Response(body=collector.exposition(), headers={"Content-Type": CONTENT_TYPE_LATEST})

    add_read(app, METRICS_PATH, metrics)
