"""The hop and journey series of /metrics only grow: each frame a join shows counts once, though
successive joins look at overlapping windows of the runs' crossings (relay.export.hopmetrics)."""

from __future__ import annotations

import numpy as np
import pytest
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families

from dcuscope.model.journeys import Hop, Joined, Journey
from dcuscope.relay.export.hopmetrics import HopMetrics

MS = 1_000_000
BOUNDS = np.array([5 * MS, 20 * MS, 50 * MS], np.int64)


def joined(arrived_ms: list[int], delay_ms: int, lost_ms: list[int], ends_ms: list[int]) -> Joined:
    hop = Hop("net A → B", "A", "B", "net", delays_ns=[delay_ms * MS] * len(arrived_ms),
              sent_ns=[(t - delay_ms) * MS for t in arrived_ms], arrived_ns=[t * MS for t in arrived_ms],
              lost_ns=[t * MS for t in lost_ms], clock_error_ns=80_000)
    journeys = [Journey(start_ns=(t - 30) * MS, end_ns=t * MS, parts=[("A", 30 * MS)], nodes=["A", "B"]) for t in ends_ms]
    return Joined({hop.name: hop}, journeys, {}, {})


def scrape(metrics: HopMetrics) -> dict:
    class Collector:
        def collect(self):
            yield from metrics.families()

    registry = CollectorRegistry(auto_describe=False)
    registry.register(Collector())
    return {s.name + str(sorted(s.labels.items())): s.value
            for f in text_string_to_metric_families(generate_latest(registry).decode()) for s in f.samples}


def test_overlapping_joins_count_each_frame_once():
    metrics = HopMetrics(BOUNDS, ["0.005", "0.02", "0.05", "+Inf"])
    metrics.update(joined([100, 140, 180], 21, lost_ms=[120], ends_ms=[110, 150, 190]))
    metrics.update(joined([140, 180, 220, 260], 21, lost_ms=[120, 200], ends_ms=[150, 190, 230, 270]))
    got = scrape(metrics)
    labels = "[('from', 'A'), ('to', 'B'), ('transport', 'net')]"
    assert got["dcuscope_hop_delay_seconds_count" + labels] == 5
    le = "[('from', 'A'), ('le', '{}'), ('to', 'B'), ('transport', 'net')]"
    assert got["dcuscope_hop_delay_seconds_bucket" + le.format("0.05")] == 5
    assert got["dcuscope_hop_delay_seconds_bucket" + le.format("0.02")] == 0
    assert got["dcuscope_hop_delay_seconds_sum" + labels] == pytest.approx(5 * 0.021)
    assert got["dcuscope_hop_lost_frames_total" + labels] == 2
    assert got["dcuscope_hop_clock_error_seconds" + labels] == 80e-6
    assert got["dcuscope_journey_delay_seconds_count[('path', 'A → B')]"] == 5
