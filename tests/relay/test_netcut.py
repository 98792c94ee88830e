"""Network cuts shorter than the node's buffer lose nothing: reset-and-refuse, and black hole."""

from __future__ import annotations

import time

import numpy as np
import pytest

from dcuscope.model.delays import node_stats
from dcuscope.relay.store.runs import load_runs
from tests.relay.helpers import (RelayProcess, assert_stats_equal, finish_node, get_json, load_node, sort_events,
                                 start_node, wait_for)
from tests.relay.netcut import CutProxy


@pytest.mark.parametrize("mode, seconds", [("refuse", 3.0), ("blackhole", 5.0)])
def test_cut_network_loses_nothing(tmp_path, mode, seconds):
    relay = RelayProcess(tmp_path / "relay.db")
    proxy = CutProxy(relay.port)
    try:
        node = start_node(proxy.url, "DCU-1", tmp_path / "n.npz", frames=400, sources=2, fps=50, paced=True)
        wait_for(lambda: get_json(f"{relay.url}/api/nodes") and get_json(f"{relay.url}/api/nodes")[0]["events"] > 1000,
                 20, what="events before the cut")
        proxy.cut(mode)
        time.sleep(seconds)
        cut_at = get_json(f"{relay.url}/api/nodes")[0]["events"]
        proxy.restore()
        counters = finish_node(node, 90)
        assert counters["lost"] == 0 and counters["acked"] == counters["events"]
        # refuse: the node saw its connection reset; black hole: the relay was silent (protocol.wire.SILENCE_S).
        # Either way it reconnected and resumed.
        assert counters["connects"] >= 2
        header, events = load_node(tmp_path / "n.npz")
        assert cut_at < len(events)
        wait_for(lambda: get_json(f"{relay.url}/api/nodes")[0]["ended"], 10, what="end of run")
        assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/stats?node=DCU-1"))
    finally:
        proxy.close()
        relay.stop()
    (run,) = load_runs(tmp_path / "relay.db", 1, corrected=False)
    assert np.array_equal(sort_events(run.events), sort_events(events))
