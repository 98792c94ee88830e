"""Two node processes feed one relay process: per-node /api/stats equals node_stats of what each sent."""

from __future__ import annotations

import numpy as np

from dcuscope.model.delays import node_stats
from dcuscope.relay.store.runs import load_runs, load_session
from tests.relay.helpers import (RelayProcess, assert_stats_equal, finish_node, get_json, http_status, load_node,
                                 sort_events, start_node, wait_for)


def test_two_nodes_stats_nodes_sessions_and_storage(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate")
    try:
        nodes = {
            "DCU-1": start_node(relay.url, "DCU-1", tmp_path / "n1.npz", frames=300, sources=2, fps=60,
                                paced=True, drop_rate=0.02, seed=1),
            "DCU-2": start_node(relay.url, "DCU-2", tmp_path / "n2.npz", frames=200, sources=3, fps=60,
                                paced=True, drop_rate=0.05, seed=2),
        }
        results = {name: finish_node(p, 60) for name, p in nodes.items()}
        for name, counters in results.items():
            assert counters["acked"] == counters["events"] and counters["lost"] == 0, counters
            header, events = load_node(tmp_path / ("n1.npz" if name == "DCU-1" else "n2.npz"))
            stats = get_json(f"{relay.url}/api/stats?node={name}")
            assert_stats_equal(node_stats(header, events), stats)
            assert stats["bottleneck"]["stage"] == "infer"
            assert stats["window"]["frames"]["complete"] > 0
            frames = get_json(f"{relay.url}/api/frames?node={name}&since=0&limit=50")
            assert [f["n"] for f in frames["frames"]] == list(range(1, 51)) and frames["stages"] == header.stages
            assert frames["cursor"] == 50 and frames["newest"] == stats["frames"]["complete"]
            page = get_json(f"{relay.url}/api/frames?node={name}&since=50&limit=50")
            assert page["frames"][0]["n"] == 51 and page["cursor"] == 100

        listed = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
        assert set(listed) == {"DCU-1", "DCU-2"}
        for name, n in listed.items():
            assert n["ended"] and n["events"] == results[name]["events"] and n["drops"] == 0
            assert n["clock"]["samples"] >= 8 and n["clock"]["uncertainty_us"] < 50_000
            assert n["ptp"]["state"] in ("unavailable", "locked", "unlocked")

        sessions = get_json(f"{relay.url}/api/sessions")
        assert len(sessions) == 1 and {r["node"] for r in sessions[0]["runs"]} == {"DCU-1", "DCU-2"}

        # The stored session, browsed from storage: same statistics, every complete frame once.
        stored = {n["node"]: n for n in get_json(f"{relay.url}/api/sessions/1/nodes")}
        assert set(stored) == {"DCU-1", "DCU-2"}
        for name, out in (("DCU-1", "n1.npz"), ("DCU-2", "n2.npz")):
            header, events = load_node(tmp_path / out)
            expected = node_stats(header, events)
            assert stored[name]["frames"] == expected["frames"]["complete"] and stored[name]["events"] == len(events)
            assert_stats_equal(expected, get_json(f"{relay.url}/api/sessions/1/stats?node={name}"))
            pages, since = [], 0
            while True:
                page = get_json(f"{relay.url}/api/sessions/1/frames?node={name}&since={since}&limit=150")
                if not page["frames"]:
                    break
                pages += page["frames"]
                since = page["cursor"]
            live = get_json(f"{relay.url}/api/frames?node={name}&limit=2000")["frames"]
            assert [f["n"] for f in pages] == list(range(1, len(live) + 1))
            strip = lambda f: {k: v for k, v in f.items() if k != "n"}  # noqa: E731
            assert sorted(map(str, map(strip, pages))) == sorted(map(str, map(strip, live)))
        assert http_status(f"{relay.url}/api/sessions/99/nodes") == 404
        assert http_status(f"{relay.url}/api/sessions/1/stats?node=nobody") == 404
    finally:
        assert relay.stop() == 0

    # After the relay stopped, the session reads back from the database alone.
    runs = {r.header.node: r for r in load_runs(tmp_path / "relay.db", 1, corrected=False)}
    for name, out in (("DCU-1", "n1.npz"), ("DCU-2", "n2.npz")):
        _, events = load_node(tmp_path / out)
        assert np.array_equal(sort_events(runs[name].events), sort_events(events))
    assert len(load_session(tmp_path / "relay.db", 1)) == 2


def test_a_node_started_before_its_relay_delivers_everything(tmp_path):
    from tests.ports import free_port
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    node = start_node(url, "early", tmp_path / "n.npz", frames=100, fps=50, paced=True)
    import time
    time.sleep(1.0)  # the node retries with backoff meanwhile
    relay = RelayProcess(tmp_path / "relay.db", port=port)
    try:
        counters = finish_node(node, 60)
        assert counters["acked"] == counters["events"] and counters["connects"] == 1
        header, events = load_node(tmp_path / "n.npz")
        wait_for(lambda: get_json(f"{url}/api/nodes")[0]["ended"], 10, what="end of run")
        assert_stats_equal(node_stats(header, events), get_json(f"{url}/api/stats?node=early"))
    finally:
        relay.stop()
