"""kill -9 of the relay mid-run: after a restart on the same database every event is stored
exactly once; an outage longer than the node's buffer loses events, counted and reported."""

from __future__ import annotations

import time

import numpy as np

from dcuscope.model.delays import node_stats
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.relay.store.runs import load_runs
from tests.ports import free_port
from tests.relay.helpers import (RelayProcess, assert_stats_equal, finish_node, get_json, load_node, sort_events,
                                 start_node, wait_for)


def test_kill9_and_restart_loses_and_duplicates_nothing(tmp_path):
    db, port = tmp_path / "relay.db", free_port()
    relay = RelayProcess(db, port=port)
    node = start_node(relay.url, "DCU-1", tmp_path / "n.npz", frames=250, sources=2, fps=50, paced=True,
                      drop_rate=0.02)
    try:
        wait_for(lambda: get_json(f"{relay.url}/api/nodes") and get_json(f"{relay.url}/api/nodes")[0]["events"] > 2000,
                 20, what="events before the kill")
        relay.kill9()
        time.sleep(1.5)
        relay = RelayProcess(db, port=port)
        counters = finish_node(node, 90)
        assert counters["connects"] >= 2 and counters["lost"] == 0
        assert counters["acked"] == counters["events"]
        header, events = load_node(tmp_path / "n.npz")
        wait_for(lambda: get_json(f"{relay.url}/api/nodes")[0]["ended"], 10, what="end of run")
        # The live state was rebuilt from storage, then continued.
        assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/stats?node=DCU-1"))
        sessions = get_json(f"{relay.url}/api/sessions")
        assert len(sessions) == 1 and len(sessions[0]["runs"]) == 1
    finally:
        relay.stop()
        if node.poll() is None:
            node.kill()
    (run,) = load_runs(db, 1, corrected=False)
    assert len(run.events) == len(events)
    assert np.array_equal(sort_events(run.events), sort_events(events))


def test_outage_beyond_the_buffer_is_counted_and_reported(tmp_path):
    db, port = tmp_path / "relay.db", free_port()
    relay = RelayProcess(db, port=port)
    # ~1,200 events/s against a 1,500-event buffer: a 4 s outage cannot be bridged.
    node = start_node(relay.url, "DCU-1", tmp_path / "n.npz", frames=300, sources=2, fps=50, paced=True,
                      extra=["--max-buffer-events", "1500", "--batch-events", "256", "--no-spool"])
    try:
        wait_for(lambda: get_json(f"{relay.url}/api/nodes") and get_json(f"{relay.url}/api/nodes")[0]["events"] > 1000,
                 20, what="events before the kill")
        relay.kill9()
        time.sleep(4.0)
        relay = RelayProcess(db, port=port)
        counters = finish_node(node, 90, status=UNACKNOWLEDGED_STATUS)
        assert counters["lost"] > 1000
        assert counters["acked"] + counters["lost"] == counters["events"]
        nodes = wait_for(lambda: [n for n in get_json(f"{relay.url}/api/nodes") if n["ended"]], 10, what="end")
        assert nodes[0]["lost"] == counters["lost"] and nodes[0]["drops"] >= counters["lost"]
    finally:
        relay.stop()
        if node.poll() is None:
            node.kill()
    (run,) = load_runs(db, 1, corrected=False)
    _, sent = load_node(tmp_path / "n.npz")
    assert run.lost == counters["lost"] and len(run.events) == counters["acked"]
    stored = sort_events(run.events)
    assert len(np.unique(stored)) == len(stored)  # nothing twice
    assert np.isin(stored, sent).all()  # nothing invented
