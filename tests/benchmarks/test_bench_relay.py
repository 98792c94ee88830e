"""benchmarks/bench_relay.py: every simulated node connects from 127.0.0.1, so the relay it starts
(bench_ui.py's too) must take more than the per-address default (16) of connections at once; and
its --quick run of two relays on PostgreSQL (and Redis), with SQLite and two relays refused as a
whole, whose figures are each a number or n/a with the reason."""

from __future__ import annotations

import http.client
import re
import urllib.parse

import pytest

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


STORE_SETTINGS = ("store sqlite: ", "store postgresql: ")


COMBINATIONS = [("sqlite", 2, 2, "adaptive"), ("postgresql", 2, 2, "adaptive")]


@pytest.mark.alone  # two relays, PostgreSQL, Redis and their nodes at full speed: a burst that starves the tests beside it
def test_quick_mode_prints_both_phases_per_store_relay_count_and_settings_and_every_figure_or_its_reason():
    """Every (store, relays, settings) combination gets its line; SQLite with two relays is refused, with its
    reason, and is the only n/a combination; two relays on PostgreSQL store every event, and the one /ui
    client watched gets the frames of both relays' nodes (through their Redis). (One combination run:
    docs/benchmarks-log.md has the benchmark's full runs, side by side.)"""
    done = run_benchmark("bench_relay.py", "--quick", "--store", "sqlite", "postgresql", "--relays", "2",
                         "--settings", "adaptive", timeout=300)
    assert_ran(done)
    lines = json_lines(done.stdout)
    assert [(x["store"], x["relays"], x["nodes"], x["settings"]) for x in lines] == COMBINATIONS, done.stdout
    for x in lines:
        assert set(x) == {"store", "relays", "nodes", "settings", "cpus", "load_before", "throughput", "lag"}
    refused, x = lines
    assert refused["throughput"] == refused["lag"] == "n/a (SQLite is one relay per file)"
    # The PostgreSQL server runs durable (PostgreSQL's defaults), and the output says so.
    pg = next(line for line in done.stdout.splitlines() if line.startswith(STORE_SETTINGS[1]))
    assert "fsync=on" in pg and "synchronous_commit=on" in pg, pg
    assert any(line.startswith(STORE_SETTINGS[0]) for line in done.stdout.splitlines())
    tp, lag = x["throughput"], x["lag"]
    assert isinstance(tp, dict) and isinstance(lag, dict), x  # only sqlite x 2 is n/a as a whole
    assert {"events", "events_per_s", "window_s", "relay_cpu_pct_in_window", "lost", "relay_cpu_us_per_event",
            "store_cpu_us_per_event"} <= set(tp)
    assert tp["events"] > 0 and tp["lost"] == 0  # two relays on one store stored every event shipped
    # in bulk the link is always busy: batches stay full with adaptive batching too (50,000 events a node)
    assert tp["events_per_batch"] >= 8192 / 2, tp
    # too short a run for a rate is n/a with its reason, never a crash (the quick run often is)
    for key in ("events_per_s", "relay_cpu_us_per_event"):
        assert isinstance(tp[key], (int, float)) or tp[key].startswith("n/a ("), (key, tp)
    assert {"lag_p50_ms", "lag_p99_ms", "push_transit_p50_ms", "frames_seen", "events_received",
            "events_in_window", "relay_cpu_us_per_event", "store_cpu_us_per_event"} <= set(lag)
    assert lag["events_received"] > 0 and lag["events_in_window"] > 0
    assert lag["nodes_seen"] == 2, lag  # the first relay's /ui gets the other's node too
    # at 4,300 events/s a node, a relay spends microseconds of CPU per event, not none and not ms
    assert 0.1 < lag["relay_cpu_us_per_event"] < 1000 and 0.1 < lag["relay_cpu_us_per_event_no_ui"] < 1000, lag
    # the server's CPU is read in clock ticks (10 ms): a 1 s window may see none
    assert 0 <= lag["store_cpu_us_per_event"] < 1000, lag
    # The side-by-side table: a row per combination and settings, the refused one n/a with its footnote.
    rows = [line.split() for line in done.stdout.splitlines() if re.match(r"(sqlite|postgresql)\s+\d", line)]
    assert [(r[0], int(r[1]), int(r[2]), r[3]) for r in rows] == COMBINATIONS, done.stdout
    refused_row = next(line for line in done.stdout.splitlines() if re.match(r"sqlite\s+2\s", line))
    refused_cells = re.findall(r"n/a \[(\d+)\]", refused_row)
    assert len(refused_cells) == 8 and len(set(refused_cells)) == 1, refused_row
    assert f"n/a [{refused_cells[0]}]: SQLite is one relay per file" in done.stdout.splitlines()
    floor = re.search(r"^compiled floor .*merge ([\d.]+) µs/event; the delay model's judgement ([\d.]+) µs/frame$",
                      done.stdout, re.M)
    assert floor and 0 < float(floor[1]) < lag["relay_cpu_us_per_event"] and float(floor[2]) > 0, done.stdout[-500:]


def test_bench_ui_starts_the_relay_of_this_benchmark_which_takes_32_nodes_and_the_browser():
    """bench_ui.py --nodes 32 was refused its page (net::ERR_CONNECTION_RESET): its relay kept the
    per-address cap of 16, which its own simulated nodes used up."""
    from benchmarks import bench_ui

    assert bench_ui.Relay is Relay


def test_tls_quick_mode_prints_the_relay_cpu_over_plaintext_and_tls_and_their_ratio():
    done = run_benchmark("bench_relay.py", "--quick", "--tls", timeout=180)
    assert_ran(done)
    (line,) = json_lines(done.stdout)
    cost = line["tls_cost"]
    for side in ("plain", "tls"):
        assert cost[side]["events_in_window"] > 0 and cost[side]["relay_cpu_us_per_event"] > 0, cost
    assert cost["ratio"] == round(cost["tls"]["relay_cpu_us_per_event"] / cost["plain"]["relay_cpu_us_per_event"], 3)
    assert "TLS / plain within 1.15" in done.stdout
