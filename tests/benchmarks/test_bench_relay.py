"""benchmarks/bench_relay.py: every simulated node connects from 127.0.0.1, so the relay it starts
(bench_ui.py's too) must take more than the per-address default (16) of connections at once; and
its --quick run, whose figures are each a number or n/a with the reason."""

from __future__ import annotations

import http.client
import urllib.parse

from benchmarks.bench_relay import Relay
from tests.benchmarks.smoke import assert_ran, json_lines, run_benchmark


def test_the_benchmark_relay_takes_more_than_16_connections_from_loopback_at_once(tmp_path):
    relay = Relay(tmp_path / "relay.db")
    conns = []
    try:
        host, port = urllib.parse.urlsplit(relay.url).netloc.split(":")
        for _ in range(40):  # all open at once, as 32 nodes and the benchmark's own requests are
            conn = http.client.HTTPConnection(host, int(port), timeout=10)
            conn.request("GET", "/api/health")
            conns.append(conn)
        statuses = []
        for conn in conns:
            response = conn.getresponse()
            response.read()
            statuses.append(response.status)
        assert statuses == [200] * 40
    finally:
        for conn in conns:
            conn.close()
        relay.stop()


def test_quick_mode_prints_both_phases_and_every_figure_or_its_reason():
    done = run_benchmark("bench_relay.py", "--quick")
    assert_ran(done)
    [line] = json_lines(done.stdout)
    assert line["nodes"] == 2 and set(line) == {"nodes", "cpus", "load_before", "throughput", "lag"}
    tp, lag = line["throughput"], line["lag"]
    assert {"events", "events_per_s", "window_s", "relay_cpu_pct_in_window", "lost"} <= set(tp)
    assert tp["events"] > 0 and tp["lost"] == 0
    # too short a run for a rate is n/a with its reason, never a crash (the quick run often is)
    assert isinstance(tp["events_per_s"], int) or tp["events_per_s"].startswith("n/a (")
    assert {"lag_p50_ms", "lag_p99_ms", "push_transit_p50_ms", "frames_seen", "events_received"} <= set(lag)
    assert lag["events_received"] > 0


def test_bench_ui_starts_the_relay_of_this_benchmark_which_takes_32_nodes_and_the_browser():
    """bench_ui.py --nodes 32 was refused its page (net::ERR_CONNECTION_RESET): its relay kept the
    per-address cap of 16, which its own simulated nodes used up."""
    from benchmarks import bench_ui

    assert bench_ui.Relay is Relay
