"""benchmarks/bench_relay.py's relay: every simulated node connects from 127.0.0.1, so the relay it
starts must take more than the per-address default (16) of connections at once."""

from __future__ import annotations

import http.client
import urllib.parse

from benchmarks.bench_relay import Relay


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
