"""The hops and journeys across DCUs in ``/metrics``: counters that only grow, from joins that look at a window.

The relay joins its runs' crossings of the last minute when asked (:mod:`dcuscope.relay.live.journeys`);
each scrape counts the frames a join shows that arrived after the last one it counted (per hop), and
the frames lost that were sent after the last loss it counted, and the journeys that ended after the
last one it counted (per path). So each frame counts once, with the delay the join gave it when
first counted, as long as scrapes come less than a minute apart and fewer journeys than the join
walks (NEWEST_JOURNEYS) end between two: a frame that left the window unscraped is not counted
(Prometheus's usual 15-60 s is well inside).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from dcuscope.model.journeys import Joined
from dcuscope.relay.export.exposition import BulkHistogram

NEVER = -(1 << 63)


@dataclass
class _Hop:
    labels: list[str]
    cumulative: np.ndarray
    total_ns: int = 0
    lost: int = 0
    arrived_upto: int = NEVER
    lost_upto: int = NEVER
    clock_error_ns: int | None = None


@dataclass
class _Path:
    cumulative: np.ndarray
    total_ns: int = 0
    ended_upto: int = NEVER


@dataclass
class HopMetrics:
    """Per hop (from, to, transport): a histogram of its delays, its lost frames, its clock error;
    per path of DCUs, a histogram of the journeys' end-to-end delays (counted by their end)."""

    bounds_ns: np.ndarray
    le: Sequence[str]
    hops: dict[str, _Hop] = field(default_factory=dict)
    paths: dict[str, _Path] = field(default_factory=dict)

    def _counts(self, values_ns: np.ndarray) -> np.ndarray:
        return np.append(np.searchsorted(np.sort(values_ns), self.bounds_ns, side="right"), len(values_ns))

    def update(self, joined: Joined) -> None:
        for name, h in joined.hops.items():
            hop = self.hops.get(name)
            if hop is None:
                hop = self.hops[name] = _Hop([h.sender, h.receiver, h.transport],
                                             np.zeros(len(self.bounds_ns) + 1, np.int64))
            arrived = np.asarray(h.arrived_ns, np.int64)
            new = arrived > hop.arrived_upto
            if new.any():
                delays = np.asarray(h.delays_ns, np.int64)[new]
                hop.cumulative += self._counts(delays)
                hop.total_ns += int(delays.sum())
                hop.arrived_upto = int(arrived.max())
            lost = [t for t in h.lost_ns if t > hop.lost_upto]
            if lost:
                hop.lost += len(lost)
                hop.lost_upto = max(lost)
            hop.clock_error_ns = h.clock_error_ns
        ended: dict[str, list[tuple[int, int]]] = {}
        for j in joined.journeys:
            ended.setdefault(" → ".join(j.nodes), []).append((j.end_ns, j.total_ns))
        for name, pairs in ended.items():
            path = self.paths.get(name)
            if path is None:
                path = self.paths[name] = _Path(np.zeros(len(self.bounds_ns) + 1, np.int64))
            new = np.array([total for end, total in pairs if end > path.ended_upto], np.int64)
            if len(new):
                path.cumulative += self._counts(new)
                path.total_ns += int(new.sum())
                path.ended_upto = max(end for end, _ in pairs)

    def families(self) -> Iterator[Metric]:
        if not self.hops:
            return
        labels = ["from", "to", "transport"]
        delay = BulkHistogram("dcuscope_hop_delay_seconds", "A frame's hop from one DCU's pipeline to another's: from "
                              "the push that sent it returning to its first packet (buffer) arriving, on the relay's "
                              "clock", labels, self.le)
        lost = CounterMetricFamily("dcuscope_hop_lost_frames", "Frames sent between two the receiver got that it never "
                                   "got", labels=labels)
        error = GaugeMetricFamily("dcuscope_hop_clock_error_seconds", "The two DCUs' clock bounds added: a hop's delay "
                                  "is true within it", labels=labels)
        for hop in self.hops.values():
            delay.add_series(hop.labels, hop.cumulative, hop.total_ns / 1e9)
            lost.add_metric(hop.labels, hop.lost)
            if hop.clock_error_ns is not None:
                error.add_metric(hop.labels, hop.clock_error_ns / 1e9)
        journey = BulkHistogram("dcuscope_journey_delay_seconds", "A frame's journey across DCUs: from its first "
                                "origin to its end on the last DCU, on the relay's clock", ["path"], self.le)
        for name, path in self.paths.items():
            journey.add_series([name], path.cumulative, path.total_ns / 1e9)
        yield from (delay, lost, error, journey)
