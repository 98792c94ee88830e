"""The namespace harness (tests/relay/nsnet.py) cuts one TCP path and nothing else: a relay in a
namespace of its own, its store black-holed, still answers from the host and is healthy again once
the cut ends; a cut in a client's namespace blocks that port only; nothing is left behind."""

from __future__ import annotations

import subprocess
import sys
import time

import psycopg
import pytest

from tests.pgserver import PostgresServer
from tests.relay.helpers import RelayProcess, get_json, wait_for
from tests.relay.nsnet import Forward, Namespace, netns_permitted

REACH = ("import sys, urllib.request\n"
         "urllib.request.urlopen(sys.argv[1], timeout=float(sys.argv[2])).read()")
CONNECT = ("import socket, sys\n"
           "socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=float(sys.argv[3])).close()")


def host_state() -> tuple[str, str]:
    """The host's firewall rules and namespaces, read only."""
    rules = subprocess.run(["iptables", "-S"], capture_output=True, text=True, timeout=20).stdout
    return rules, subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=20).stdout


def healthy(url: str) -> bool:
    try:
        return get_json(f"{url}/api/health", timeout=2)["ok"]
    except OSError:
        return False


def store_clock(pg: PostgresServer):
    with psycopg.connect(pg.url(), autocommit=True) as conn:
        return conn.execute("SELECT clock_timestamp()").fetchone()[0]


def queried_since(pg: PostgresServer, client: str, since) -> bool:
    """Whether a connection from ``client`` began a query after ``since`` (the server's clock)."""
    with psycopg.connect(pg.url(), autocommit=True) as conn:
        return conn.execute("SELECT EXISTS (SELECT 1 FROM pg_stat_activity WHERE client_addr = %s"
                            " AND query_start > %s)", (client, since)).fetchone()[0]


def test_a_cut_store_and_a_cut_client_port(tmp_path):
    why = netns_permitted()
    if why is not None:
        pytest.skip(why)
    before = host_state()
    with Namespace() as relay_ns, Namespace() as client_ns:
        names = (relay_ns.name, client_ns.name)
        assert relay_ns.network != client_ns.network
        pg = PostgresServer(listen=[relay_ns.host_addr, client_ns.host_addr]).start()
        try:
            relay = RelayProcess(pg.new_database(relay_ns.host_addr), log=tmp_path / "relay.log",
                                 prefix=relay_ns.prefix, args=["--host", relay_ns.ns_addr])
            try:
                assert relay.url == f"http://{relay_ns.ns_addr}:{relay.port}"
                assert get_json(f"{relay.url}/api/health", timeout=5)["ok"]

                # The store black-holed: the relay's fleet refresh (once a second) goes unanswered,
                # yet its HTTP API answers the host at once. The cut is kept to about a second, under
                # the store connection's TCP timeouts: after a longer one an idle relay reconnects but
                # its /api/health stays not ok (a stale storage error), which is issue 32's to judge.
                relay_ns.drop(pg.port)
                wait_for(relay_ns.dropped, 10, what="the relay's packets to PostgreSQL dropped")
                t0 = time.monotonic()
                assert "ok" in get_json(f"{relay.url}/api/health", timeout=2)
                assert time.monotonic() - t0 < 2
                restored = store_clock(pg)
                relay_ns.restore()
                assert relay_ns.dropped() == 0  # the rules, their counters with them, are gone
                wait_for(lambda: queried_since(pg, relay_ns.ns_addr, restored), 30, interval=0.5,
                         what="the relay's queries reaching PostgreSQL again")
                wait_for(lambda: healthy(relay.url), 30, interval=0.5, what="the relay healthy after the cut")

                # A client in another namespace reaches the relay through the host; its relay port cut,
                # its PostgreSQL port is not.
                with Forward((client_ns.host_addr, relay.port), (relay.host, relay.port)):
                    health = f"http://{client_ns.host_addr}:{relay.port}/api/health"

                    def reach(*argv: str) -> subprocess.CompletedProcess:
                        return client_ns.run(sys.executable, "-c", *argv, timeout=20)

                    first = reach(REACH, health, "5")
                    assert first.returncode == 0, first.stderr[-500:]
                    client_ns.drop(relay.port)
                    cut = reach(REACH, health, "1")
                    assert cut.returncode != 0 and "timed out" in cut.stderr, cut.stderr[-500:]
                    assert client_ns.dropped() > 0
                    assert reach(CONNECT, client_ns.host_addr, str(pg.port), "5").returncode == 0
                    client_ns.restore()
                    assert reach(REACH, health, "5").returncode == 0
            finally:
                relay.stop()
        finally:
            pg.close()
    after = host_state()
    assert after[0] == before[0], "the host's firewall changed"
    assert not any(name in after[1] for name in names), after[1]
