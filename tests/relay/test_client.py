"""RelayExporter on its own: write never blocks, the buffer is bounded, losses are counted."""

from __future__ import annotations

import time

import numpy as np
import pytest

from relay.client import RelayExporter
from relay.errors import RelayError
from relay.simnode import header_for, synth_events
from tests.relay.helpers import free_port

T0 = 1_700_000_000_000_000_000


def test_unreachable_relay_write_returns_at_once_and_losses_are_counted():
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    exporter = RelayExporter(url, "lonely", max_buffer_events=5_000, batch_events=1000, close_timeout_s=1.0)
    exporter.start(header_for("lonely", 2))
    events = synth_events(2000, 2, 25.0, T0)  # 48,000 events
    worst = 0.0
    for i in range(0, len(events), 500):
        t = time.perf_counter()
        exporter.write(events[i:i + 500])
        worst = max(worst, time.perf_counter() - t)
        time.sleep(0.002)
    assert worst < 0.05, f"write took {worst * 1e3:.1f} ms"
    time.sleep(0.3)
    c = exporter.counters()
    assert not c["connected"] and c["acked"] == 0 and "cannot reach relay" in c["last_error"]
    assert c["buffered"] <= 5_000 + 1000 and c["lost"] >= len(events) - 6_000
    t = time.perf_counter()
    exporter.close(dropped=3)
    assert time.perf_counter() - t < 5.0
    assert exporter.counters()["written"] == len(events)


def test_bad_arguments_are_user_errors():
    with pytest.raises(RelayError, match="http://"):
        RelayExporter("127.0.0.1:3000", "n")
    with pytest.raises(RelayError, match="unknown clock"):
        RelayExporter("http://127.0.0.1:3000", "n", clock="sundial")
    exporter = RelayExporter("http://127.0.0.1:1", "n")
    with pytest.raises(ValueError, match="EVENT_DTYPE"):
        exporter.write(np.zeros(3, np.int64))
    exporter.close(0)  # never started: nothing to do
