"""Starvation and hostile requests (issue 12, items 6 and 8) against a real relay process on
loopback, with a well-behaved simulated node streaming beside the attacker: the node's events
are all acknowledged and its statistics exact, whatever the attacker does.

Attackers connect from other loopback addresses (127.0.0.2, 127.0.x.y), so that the per-peer
cap is what it would be on a network: a bound on one address, not on the good node.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import resource
import selectors
import socket
import time
from pathlib import Path

import pytest

from dcuscope.core.pycompat import ASYNC_TIMEOUTS, timeout
from dcuscope.model.delays import node_stats
from tests.relay.helpers import (RelayProcess, assert_stats_equal, finish_node, get_json, load_node, read_http_answer,
                                 start_node, wait_for)

TOKEN = "s3cret"
WS_KEY = "dGhlIHNhbXBsZSBub25jZQ=="


# --- raw HTTP, to send exactly what an attacker sends -------------------------------------------

def raw_request(path: str, host: str | None, headers: dict[str, str | bytes] | None = None) -> bytes:
    lines = [f"GET {path} HTTP/1.1".encode()]
    if host is not None:
        lines.append(b"Host: " + host.encode())
    headers = {"Connection": "close", **(headers or {})}
    for name, value in headers.items():
        lines.append(name.encode() + b": " + (value if isinstance(value, bytes) else value.encode()))
    return b"\r\n".join([*lines, b"", b""])


def upgrade_headers(extra: dict | None = None) -> dict:
    return {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Key": WS_KEY,
            "Sec-WebSocket-Version": "13", **(extra or {})}


def raw_get(port: int, path: str, host: str | None = "127.0.0.1", headers: dict | None = None,
            source: str = "127.0.0.1") -> tuple[int, bytes]:
    """Status and body of one request (no body for a 101)."""
    with socket.create_connection(("127.0.0.1", port), 10, source_address=(source, 0)) as s:
        s.sendall(raw_request(path, host, headers))
        answer = read_http_answer(s)
    assert answer, f"no HTTP answer to {path[:80]}"
    return answer


# --- the good node --------------------------------------------------------------------------------

def good_node(url: str, tmp_path: Path, token: str | None = None, frames: int = 150):
    return start_node(url, "good", tmp_path / "good.npz", frames=frames, sources=2, fps=25, paced=True, token=token)


def check_good_node(relay: RelayProcess, proc, tmp_path: Path, token: str | None = None, timeout: float = 40) -> None:
    counters = finish_node(proc, timeout)
    assert counters["acked"] == counters["events"] and counters["lost"] == 0 and counters["connects"] == 1, counters
    header, events = load_node(tmp_path / "good.npz")
    try:  # a bound only: the end is answered at once on a quiet machine
        wait_for(lambda: get_json(f"{relay.url}/api/nodes", token)[0]["ended"], 20, what="end of the good run")
    except AssertionError as exc:  # what the node and the relay said, for a run that never ends
        raise AssertionError(f"{exc}; node: {counters}; relay log: {relay.log.read_text(errors='replace')[-3000:]}") from None
    assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/stats?node=good", token))


def health(relay: RelayProcess, token: str | None = None, timeout: float = 5) -> dict:
    return get_json(f"{relay.url}/api/health", token, timeout)


def assert_quiet_log(relay: RelayProcess, max_lines: int = 30) -> None:
    text = relay.log.read_text(errors="replace")
    assert "Traceback" not in text, text[-3000:]
    assert len(text.splitlines()) <= max_lines, text[-3000:]


# --- (a) ingest connections that never say hello -------------------------------------------------

async def open_squatters(port: int, n: int, source: str) -> tuple[list, int]:
    """``n`` WebSocket upgrades of /ingest from ``source`` that never say hello: the upgraded ones
    (reader, writer, time of the upgrade) and how many were refused (503, or closed at once)."""
    gate = asyncio.Semaphore(128)

    async def one():
        async with gate:
            try:
                reader, writer = await asyncio.wait_for(
                    asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0)), 10)
                writer.write(raw_request("/ingest", f"127.0.0.1:{port}", upgrade_headers()))
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
            except (OSError, asyncio.IncompleteReadError):
                return None
            if head.startswith(b"HTTP/1.1 101"):
                return reader, writer, time.monotonic()
            writer.close()
            return None

    results = await asyncio.gather(*(one() for _ in range(n)))
    upgraded = [r for r in results if r is not None]
    return upgraded, n - len(upgraded)


async def until_closed(reader: asyncio.StreamReader, limit_s: float) -> tuple[float, bytes]:
    """Seconds until the relay closes the connection (at most ``limit_s``) and what it sent."""
    start, data = time.monotonic(), b""
    try:
        async with timeout(limit_s):
            while chunk := await reader.read(4096):
                data += chunk
    except (*ASYNC_TIMEOUTS, OSError):
        pass
    return time.monotonic() - start, data


@pytest.mark.alone  # 1,023 connections opened within the 2 s hello timeout: a loaded machine frees places meanwhile
def test_never_hello_connections_are_closed_and_a_node_gets_in(tmp_path):
    hello_s = 2.0
    # The per-peer cap raised: here the hello timeout alone must free the ingest places.
    # INFO: each connection it closes is a log line, 256 of the same: the log rate bound holds them.
    relay = RelayProcess(tmp_path / "relay.db", args=["--limit", f"hello_timeout_s={hello_s}", "--log-level", "INFO",
                                                      "--limit", "connections_per_peer=2000"])
    try:
        async def attack():
            upgraded, refused = await open_squatters(relay.port, 1023, "127.0.0.2")
            node = good_node(relay.url, tmp_path)  # while every ingest place is taken
            closes = await asyncio.gather(*(until_closed(r, hello_s + 6) for r, _, _ in upgraded))
            for _, w, _ in upgraded:
                w.close()
            return upgraded, refused, node, closes

        upgraded, refused, node, closes = asyncio.run(attack())
        limits = health(relay)["limits"]
        assert len(upgraded) == limits["connections"] and refused == 1023 - len(upgraded)
        # Closed with an error message once the hello is overdue (plus the close handshake's wait).
        assert all(b"hello" in data for _, data in closes), closes[0]
        assert max(t for t, _ in closes) < hello_s + 5, max(t for t, _ in closes)
        check_good_node(relay, node, tmp_path)
        h = health(relay)
        assert h["refused"]["hello_timeout"] == len(upgraded), h["refused"]
        assert h["connections"]["ingest"] == 0
        print(f"\nnever-hello x1023: peak RSS {relay.peak_rss_mb():.0f} MB")
        relay.stop()  # the relay summarises what it held back as it stops
        assert_quiet_log(relay)
        assert re.search(r"suppressed \d+ similar messages in 60 s: ingest: closing", relay.log.read_text())
    finally:
        relay.stop()


def test_one_address_cannot_take_the_ingest_places(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db")  # default limits: 16 connections per address
    try:
        async def attack():
            upgraded, refused = await open_squatters(relay.port, 1023, "127.0.0.2")
            node = good_node(relay.url, tmp_path)
            return upgraded, refused, node

        upgraded, refused, node = asyncio.run(attack())
        assert len(upgraded) <= 16 and refused >= 1023 - 16
        check_good_node(relay, node, tmp_path)
        h = health(relay)
        assert h["refused"]["peer_cap"] >= 1023 - 16, h["refused"]
        assert_quiet_log(relay)
        print(f"\none address x1023: peak RSS {relay.peak_rss_mb():.0f} MB")
    finally:
        relay.stop()


def test_a_hosts_idle_connections_make_room_for_its_next_ones_its_busy_ones_do_not(tmp_path):
    """A browser keeps its page's connections open once loaded (six a page, for ``keepalive_s``), so
    a host at its cap with idle ones closes its longest idle one for the next (the third page of a
    laptop loads); connections that are busy (a WebSocket here) hold their places."""
    relay = RelayProcess(tmp_path / "relay.db", args=["--limit", "connections_per_peer=2",
                                                      "--limit", "hello_timeout_s=60"])
    kept: list[socket.socket] = []
    try:
        for _ in range(3):
            kept.append(socket.create_connection(("127.0.0.1", relay.port), 10, source_address=("127.0.0.2", 0)))
            kept[-1].sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert read_http_answer(kept[-1])[0] == 200  # kept alive, idle: the third is served too
        kept[0].settimeout(5)
        assert kept[0].recv(1) == b""  # the longest-idle one made room
        for s in kept[1:]:
            s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert read_http_answer(s)[0] == 200

        async def busy_then_third():
            upgraded, refused = await open_squatters(relay.port, 2, "127.0.0.3")
            third, _ = await open_squatters(relay.port, 1, "127.0.0.3")
            return upgraded, third

        upgraded, third = asyncio.run(busy_then_third())
        assert len(upgraded) == 2 and third == [], (upgraded, third)
        h = health(relay)
        assert h["refused"]["peer_cap"] == 2, h["refused"]
        assert_quiet_log(relay)
    finally:
        for s in kept:
            s.close()
        relay.stop()


# --- (b) silent TCP connections against a 1024-descriptor relay ---------------------------------

def test_silent_connections_do_not_exhaust_descriptors(tmp_path):
    n, nofile = 1100, 1024
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = n + 200  # this process holds the attacker's sockets
    if soft != resource.RLIM_INFINITY and soft < need:
        if hard != resource.RLIM_INFINITY and hard < need:
            pytest.skip(f"the test needs {need} file descriptors, the hard limit is {hard}")
        resource.setrlimit(resource.RLIMIT_NOFILE, (need, hard))
    relay = RelayProcess(tmp_path / "relay.db", prefix=["prlimit", f"--nofile={nofile}:{nofile}"])
    socks: list[socket.socket] = []
    try:
        node = good_node(relay.url, tmp_path)
        wait_for(lambda: get_json(f"{relay.url}/api/nodes"), 20, what="the good node")
        for i in range(n):  # one per address: the per-peer cap does not apply, the total one does
            s = socket.socket()
            socks.append(s)
            s.settimeout(10)
            s.bind((f"127.0.{1 + i // 200}.{2 + i % 200}", 0))
            s.connect(("127.0.0.1", relay.port))
        for _ in range(3):
            h = health(relay)
            fds = len(os.listdir(f"/proc/{relay.proc.pid}/fd"))
            assert fds < nofile and h["connections"]["tcp"] <= h["limits"]["tcp_connections"] < nofile, (fds, h)
            time.sleep(0.5)
        assert h["refused"]["tcp_cap"] >= n - h["limits"]["tcp_connections"], h["refused"]
        check_good_node(relay, node, tmp_path)
        assert_quiet_log(relay)
        print(f"\nsilent TCP x{n}: peak RSS {relay.peak_rss_mb():.0f} MB, tcp_connections "
              f"{h['limits']['tcp_connections']}, fds {fds}")
    finally:
        for s in socks:
            s.close()
        relay.stop()


# --- (c) slowloris ---------------------------------------------------------------------------------

def test_half_open_requests_are_closed(tmp_path):
    header_s, keepalive_s = 1.5, 2.0
    relay = RelayProcess(tmp_path / "relay.db", args=["--limit", f"header_timeout_s={header_s}",
                                                      "--limit", f"keepalive_s={keepalive_s}"])
    sel = selectors.DefaultSelector()
    try:
        node = good_node(relay.url, tmp_path)
        kinds: dict[socket.socket, str] = {}
        for kind, count in (("trickle", 8), ("silent", 4), ("idle", 2)):
            for _ in range(count):
                s = socket.create_connection(("127.0.0.1", relay.port), 5, source_address=("127.0.0.3", 0))
                kinds[s] = kind
                if kind == "trickle":
                    s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
                elif kind == "idle":  # one whole request, then nothing on the kept-alive connection
                    s.sendall(raw_request("/api/health", "127.0.0.1").replace(b"Connection: close", b"X: y"))
                s.setblocking(False)
                sel.register(s, selectors.EVENT_READ)
        started, closed = time.monotonic(), {}
        while len(closed) < len(kinds) and time.monotonic() - started < 10:
            for key, _ in sel.select(0.25):
                try:
                    more = key.fileobj.recv(65536)
                except ConnectionError:
                    more = b""
                if not more:
                    closed[key.fileobj] = time.monotonic() - started
                    sel.unregister(key.fileobj)
            for s, kind in kinds.items():  # a header line now and then: never a complete head
                if kind == "trickle" and s not in closed:
                    try:
                        s.send(b"X-Slow: 1\r\n")
                    except OSError:
                        pass
        by_kind = {k: [closed.get(s) for s, kind in kinds.items() if kind == k] for k in ("trickle", "silent", "idle")}
        assert None not in by_kind["trickle"] + by_kind["silent"], by_kind
        assert max(by_kind["trickle"] + by_kind["silent"]) < header_s + 2, by_kind
        assert None not in by_kind["idle"] and max(by_kind["idle"]) < keepalive_s + 2, by_kind
        check_good_node(relay, node, tmp_path)
        assert health(relay)["refused"]["header_timeout"] >= 12
        assert_quiet_log(relay)
        print(f"\nslowloris: peak RSS {relay.peak_rss_mb():.0f} MB")
    finally:
        for key in list(sel.get_map().values()):
            key.fileobj.close()
        relay.stop()


# --- (d) undecodable tokens, absurd ids and parameters -------------------------------------------

def test_bad_tokens_ids_and_parameters_get_4xx(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", token=TOKEN)
    try:
        node = good_node(relay.url, tmp_path, token=TOKEN, frames=50)
        check_good_node(relay, node, tmp_path, token=TOKEN)
        session = get_json(f"{relay.url}/api/nodes", TOKEN)[0]["session"]
        for value in (b"Bearer \xff\xfe\xe9", "Bearer é".encode(), b"\xc3(", "Bearer ☃".encode()):
            for path in ("/api/health", "/api/nodes", f"/api/sessions/{session}/nodes"):
                assert raw_get(relay.port, path, headers={"Authorization": value})[0] == 401, (path, value)
            assert raw_get(relay.port, "/ingest", headers=upgrade_headers({"Authorization": value}))[0] == 401
        auth = {"Authorization": f"Bearer {TOKEN}"}
        assert raw_get(relay.port, "/api/nodes?token=%FF%FE", headers={})[0] == 401
        bad = [f"/api/sessions/{'9' * 20}/nodes", f"/api/sessions/{'1' * 4301}/stats?node=good",
               f"/api/sessions/{'7' * 19}/frames?node=good", f"/api/sessions/{session}/frames?node=good&since={'9' * 5000}",
               f"/api/sessions/{session}/frames?node=good&limit=1e999", f"/api/sessions/{session}/stats?node=%FF",
               f"/api/frames?node=good&since={'9' * 4301}", "/api/frames?node=good&limit=x", "/api/stats?node=%ff%fe",
               "/api/stats?node=" + "n" * 5000, "/api/frames"]
        for path in bad:
            status, body = raw_get(relay.port, path, headers=auth)
            assert status in (400, 404) and "error" in json.loads(body), (path[:80], status, body[:200])
        # The token is the guard: any Host passes with it.
        assert raw_get(relay.port, "/api/health", host="evil.example", headers=auth)[0] == 200
        assert health(relay, TOKEN)["ok"]
        assert_quiet_log(relay)
        print(f"\nbad tokens and ids: peak RSS {relay.peak_rss_mb():.0f} MB")
    finally:
        relay.stop()


# --- (e) Host and Origin without a token ------------------------------------------------------

def test_host_and_origin_are_checked_without_a_token(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", args=["--allow-host", "relay.test"])
    port = relay.port
    try:
        node = good_node(relay.url, tmp_path, frames=50)
        sio = "/socket.io/?EIO=4&transport=polling"
        refused = [("/api/health", "evil.example", {}), ("/api/nodes", f"evil.example:{port}", {}),
                   ("/", f"evil.example:{port}", {}), (sio, f"evil.example:{port}", {}),
                   # A page of a rebound name is its own origin: its Host gives it away.
                   ("/ingest", f"evil.example:{port}", upgrade_headers({"Origin": f"http://evil.example:{port}"})),
                   ("/ingest", f"127.0.0.1:{port}", upgrade_headers({"Origin": "http://evil.example"})),
                   ("/api/nodes", f"127.0.0.1:{port}", {"Origin": f"http://evil.example:{port}"}),
                   ("/api/nodes", f"127.0.0.1:{port}", {"Origin": "null"}),
                   ("/api/nodes", f"127.0.0.1:{port}", {"Origin": f"http://localhost:{port}"})]
        for path, host, headers in refused:
            status, body = raw_get(port, path, host=host, headers=headers)
            assert status == 403 and "refused" in json.loads(body)["error"], (path, host, headers, status)
        accepted = [("/api/health", f"127.0.0.1:{port}", {}), ("/api/nodes", f"localhost:{port}", {}),
                    ("/api/nodes", f"LOCALHOST:{port}", {"Origin": f"http://localhost:{port}"}),
                    ("/api/nodes", f"[::1]:{port}", {}),
                    ("/", f"127.0.0.1:{port}", {"Origin": f"http://127.0.0.1:{port}"}),
                    (sio, f"localhost:{port}", {}), ("/api/nodes", f"relay.test:{port}", {}),
                    ("/api/nodes", f"127.0.0.1:{port}", {"Origin": "http://relay.test:8080"})]
        for path, host, headers in accepted:
            assert raw_get(port, path, host=host, headers=headers)[0] == 200, (path, host, headers)
        assert raw_get(port, "/ingest", host=f"localhost:{port}",
                       headers=upgrade_headers({"Origin": f"http://localhost:{port}"}))[0] == 101
        # A node (no Origin: not a browser) may name the relay by any host name.
        assert raw_get(port, "/ingest", host=f"monitor.example:{port}", headers=upgrade_headers())[0] == 101
        check_good_node(relay, node, tmp_path)
        assert health(relay)["refused"]["host"] == len(refused)
        assert_quiet_log(relay)
        print(f"\nhost/origin: peak RSS {relay.peak_rss_mb():.0f} MB")
    finally:
        relay.stop()
