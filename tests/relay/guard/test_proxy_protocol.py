"""The relay behind a TCP load balancer: PROXY protocol headers (v1 and v2) from ``--trusted-proxy``
peers give each connection its client's address, for the per-address caps and for aiohttp.

The proxy here is real: an asyncio TCP proxy on loopback, in a thread of its own, that connects to
the relay from :data:`PROXY_ADDR` and forwards both ways, after a header naming the client's own
source address. Clients bind to distinct loopback addresses (127.0.0.2, 127.0.0.3, ...), so each
is a host of its own as it would be on a network. The relay is a real process
(:class:`~tests.relay.helpers.RelayProcess`), except in the test that needs a handler's view of
the request (``request.remote``), which serves a small app through the guard in-process.
"""

from __future__ import annotations

import asyncio
import hashlib
import ipaddress
import json
import socket
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable

import pytest
from aiohttp import web

from dcuscope.relay.guard.connections import ConnGuard, GuardedSite
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.guard.proxy import (V1_MAX_BYTES, V2_SIGNATURE, ProxyHeader, ProxyHeaderError, TrustedProxies,
                               parse_header)
from tests.ports import free_port
from tests.relay.helpers import RelayProcess, finish_node, get_json, read_http_answer, start_node, wait_for

PROXY_ADDR = "127.0.0.9"
"""The address the proxy connects to the relay from (the one ``--trusted-proxy`` names)."""
IO_TIMEOUT_S = 10.0

pytestmark = pytest.mark.timeout(120)


# --- headers ----------------------------------------------------------------------------------------

def v1(client: tuple[str, int], relay_port: int = 3000) -> bytes:
    family = "TCP4" if ipaddress.ip_address(client[0]).version == 4 else "TCP6"
    dest = "127.0.0.1" if family == "TCP4" else "::1"
    return f"PROXY {family} {client[0]} {dest} {client[1]} {relay_port}\r\n".encode()


def v2(client: tuple[str, int] | None, relay_port: int = 3000, tlvs: bytes = b"") -> bytes:
    """A v2 PROXY header for ``client`` (None: the LOCAL command, a proxy's own connection)."""
    if client is None:
        return V2_SIGNATURE + bytes([0x20, 0x00]) + struct.pack("!H", len(tlvs)) + tlvs
    ip = ipaddress.ip_address(client[0])
    dest = ipaddress.ip_address("127.0.0.1" if ip.version == 4 else "::1")
    body = ip.packed + dest.packed + struct.pack("!HH", client[1], relay_port) + tlvs
    family = 0x11 if ip.version == 4 else 0x21  # INET or INET6, STREAM
    return V2_SIGNATURE + bytes([0x21, family]) + struct.pack("!H", len(body)) + body


# --- a real TCP proxy -----------------------------------------------------------------------------

async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter, close: bool) -> None:
    """Copy ``src`` to ``dst`` until it ends; then half-close ``dst`` (``close``: close it)."""
    try:
        while chunk := await src.read(65536):
            dst.write(chunk)
            await dst.drain()
    except (OSError, asyncio.CancelledError):
        pass
    try:
        if close or not dst.can_write_eof():
            dst.close()
        else:
            dst.write_eof()
    except OSError:
        pass


class Proxy:
    """A TCP proxy listening on 127.0.0.1: each connection is forwarded to the relay on
    ``upstream_port`` from :data:`PROXY_ADDR`, both ways, after ``header(client address)`` (None:
    no header, a plain TCP proxy)."""

    def __init__(self, upstream_port: int, header: Callable[[tuple[str, int]], bytes] | None) -> None:
        self.upstream_port = upstream_port
        self.header = header
        self.port = free_port()
        self._writers: set[asyncio.StreamWriter] = set()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        self._server = self._call(asyncio.start_server(self._serve, "127.0.0.1", self.port))

    def _call(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(IO_TIMEOUT_S)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = writer.get_extra_info("peername")
        self._writers.add(writer)
        try:
            up_reader, up_writer = await asyncio.wait_for(asyncio.open_connection(
                "127.0.0.1", self.upstream_port, local_addr=(PROXY_ADDR, 0)), IO_TIMEOUT_S)
        except OSError:
            writer.close()
            return
        self._writers.add(up_writer)
        if self.header is not None:
            up_writer.write(self.header(client[:2]))
        # The relay closing its side closes the client's (so a refused client sees it at once).
        await asyncio.gather(_pipe(reader, up_writer, close=False), _pipe(up_reader, writer, close=True))
        up_writer.close()

    async def _stop(self) -> None:
        self._server.close()
        for writer in self._writers:
            writer.close()

    def close(self) -> None:
        try:
            self._call(self._stop())
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(IO_TIMEOUT_S)


# --- clients ----------------------------------------------------------------------------------------

def connect(port: int, source: str) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), IO_TIMEOUT_S, source_address=(source, 0))


def request(sock: socket.socket, path: str = "/api/health", prefix: bytes = b"") -> tuple[int, bytes] | None:
    """Status and body of one keep-alive GET on ``sock`` (after ``prefix``); None when the
    connection is closed before an answer."""
    try:
        sock.sendall(prefix + f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        return read_http_answer(sock)
    except ConnectionError:
        return None


def closed_within(sock: socket.socket, limit_s: float) -> float | None:
    """Seconds until the other end closes ``sock`` (None: still open after ``limit_s``)."""
    start = time.monotonic()
    sock.settimeout(limit_s)
    try:
        while sock.recv(65536):
            pass
    except TimeoutError:
        return None
    except ConnectionError:
        pass
    return time.monotonic() - start


def health(relay: RelayProcess) -> dict:
    return get_json(f"{relay.url}/api/health")  # from 127.0.0.1, no proxy of the relay's


def assert_clean_log(relay: RelayProcess) -> None:
    text = relay.log.read_text(errors="replace")
    assert "Traceback" not in text, text[-3000:]


# --- the parser ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("data, client, length", [
    (b"PROXY TCP4 192.0.2.7 10.0.0.1 40000 3000\r\nGET", ("192.0.2.7", 40000), 42),
    (b"PROXY TCP6 2001:db8::7 ::1 1 65535\r\n", ("2001:db8::7", 1), 36),
    (b"PROXY TCP6 ::ffff:192.0.2.7 ::1 0 3000\r\n", ("192.0.2.7", 0), 40),  # a v6 proxy's IPv4 client
    (b"PROXY UNKNOWN\r\n", None, 15),
    (b"PROXY UNKNOWN ffff:f...f:ffff ffff:f...f:ffff 65535 65535\r\n", None, 59),
    (v2(("192.0.2.7", 40000)) + b"GET", ("192.0.2.7", 40000), 28),
    (v2(("2001:db8::7", 1)), ("2001:db8::7", 1), 52),
    (v2(("192.0.2.7", 5), tlvs=b"\x04\x00\x03abc"), ("192.0.2.7", 5), 34),  # TLVs skipped
    (v2(None), None, 16),
    (v2(None, tlvs=b"\x01" * 40), None, 56),
    (V2_SIGNATURE + bytes([0x21, 0x00, 0, 0]), None, 16),  # PROXY, UNSPEC: no address to use
    (V2_SIGNATURE + bytes([0x21, 0x31, 0, 216]) + bytes(216), None, 232),  # UNIX
])
def test_parses_valid_headers(data, client, length):
    header = parse_header(data)
    assert header == ProxyHeader(length, client, 1 if data.startswith(b"PROXY") else 2)
    for cut in range(length):  # a start of one: wait for more
        assert parse_header(data[:cut]) is None, cut


@pytest.mark.parametrize("data", [
    b"GET / HTTP/1.1\r\n", b"\x16\x03\x01", b"proxy TCP4 1.2.3.4 1.2.3.4 1 2\r\n", b"PROXY\r\n",
    b"PROXY TCP4 1.2.3.4 1.2.3.4 1 2\n", b"PROXY TCP4 1.2.3.4 1.2.3.4 1 2 3\r\n", b"PROXY TCP4 1.2.3.4  1.2.3.4 1 2\r\n",
    b"PROXY TCP4 1.2.3.4 1.2.3.4 1\r\n", b"PROXY TCP5 1.2.3.4 1.2.3.4 1 2\r\n", b"PROXY TCP4 ::1 ::1 1 2\r\n",
    b"PROXY TCP6 1.2.3.4 1.2.3.4 1 2\r\n", b"PROXY TCP4 1.2.3.256 1.2.3.4 1 2\r\n", b"PROXY TCP4 1.2.3.4 1.2.3.4 65536 2\r\n",
    b"PROXY TCP4 1.2.3.4 1.2.3.4 080 2\r\n", b"PROXY TCP4 1.2.3.4 1.2.3.4 +80 2\r\n", b"PROXY TCP4 1.2.3.4 1.2.3.4 -1 2\r\n",
    "PROXY TCP4 1.2.3.4 1.2.3.4 ٣ 2\r\n".encode(), b"PROXY TCP4 1.2.3.4\xff 1.2.3.4 1 2\r\n",
    b"PROXY UNKNOWN " + b"x" * (V1_MAX_BYTES - 15) + b"\r\n",  # 108 bytes: one too many
    b"PROXY TCP4 " + b"1" * 200,
    V2_SIGNATURE + bytes([0x11, 0x11, 0, 12]) + bytes(12),  # version 1 in a v2 signature
    V2_SIGNATURE + bytes([0x22, 0x11, 0, 12]) + bytes(12),  # command 2
    V2_SIGNATURE + bytes([0x21, 0x11, 0, 11]) + bytes(11),  # too short for two IPv4 addresses
    V2_SIGNATURE + bytes([0x21, 0x21, 0, 12]) + bytes(12),  # too short for IPv6
    V2_SIGNATURE + bytes([0x21, 0x41, 0, 0]),  # family 4
    b"\r\n\r\n\x00\r\nQUIX\n" + bytes(20),
])
def test_refuses_malformed_headers(data):
    with pytest.raises(ProxyHeaderError):
        parse_header(data)


def test_trusted_proxies_parse_and_match():
    trusted = TrustedProxies.parse(["127.0.0.9, 10.0.0.0/8", "2001:db8::/32", "127.0.0.9"])
    assert trusted.as_list() == ["127.0.0.9", "10.0.0.0/8", "2001:db8::/32"]
    assert "127.0.0.9" in trusted and "10.200.3.4" in trusted and "2001:db8::1" in trusted
    assert "::ffff:10.0.0.1" in trusted and "fe80::1%eth0" not in trusted
    assert "127.0.0.1" not in trusted and "11.0.0.1" not in trusted and "/tmp/sock" not in trusted
    assert not TrustedProxies.parse([]) and "127.0.0.1" not in TrustedProxies()
    for bad in ["lb.example", "10.0.0.1/24", "10.0.0.0/33", "1.2.3.4,", "", "1.2.3.4/8"]:
        with pytest.raises(ValueError):
            TrustedProxies.parse([bad])


# --- (a, d) each client limited by its own address, v1 and v2 --------------------------------------

@pytest.mark.parametrize("version", ["v1", "v2"])
def test_clients_behind_the_proxy_are_limited_by_their_own_addresses(tmp_path, version):
    relay = RelayProcess(tmp_path / "relay.db", args=["--trusted-proxy", f"{PROXY_ADDR},10.0.0.0/8",
                                                      "--limit", "connections_per_peer=2"])
    proxy = Proxy(relay.port, v1 if version == "v1" else v2)
    held: list[socket.socket] = []
    try:
        for _ in range(2):
            held.append(connect(proxy.port, "127.0.0.2"))
            assert request(held[-1])[0] == 200
        # 127.0.0.2's third, once the header named it: over its cap, so its longest-idle one makes room.
        third = connect(proxy.port, "127.0.0.2")
        held.append(third)
        assert request(third)[0] == 200
        assert request(held[0]) is None
        other = connect(proxy.port, "127.0.0.3")  # through the same proxy: a host of its own
        held.append(other)
        assert request(held[1])[0] == 200  # 127.0.0.3 took no place of 127.0.0.2's
        status, body = request(other)
        assert status == 200
        h = json.loads(body)
        assert h["refused"]["peer_cap"] == 1 and h["refused"]["proxy_header"] == 0, h["refused"]
        # Three connections open from the proxy's own address, over the cap of 2: the proxy is under none.
        assert h["proxy"] == {"trusted": [PROXY_ADDR, "10.0.0.0/8"], "proxied": 4, "proxied_open": 3}, h["proxy"]
        if version == "v1":
            # A node streams through the proxy too (its WebSocket upgrade and all).
            node = start_node(f"http://127.0.0.1:{proxy.port}", "behind", tmp_path / "behind.npz", frames=40)
            counters = finish_node(node, 60)
            assert counters["acked"] == counters["events"] and counters["lost"] == 0, counters
        for s in held:
            s.close()
        wait_for(lambda: health(relay)["proxy"]["proxied_open"] == 0, 10, what="proxied connections to close")
        assert_clean_log(relay)
    finally:
        for s in held:
            s.close()
        proxy.close()
        relay.stop()


# --- (b) no header is honoured from an untrusted peer ---------------------------------------------------

def test_without_trusted_proxy_a_header_is_http_garbage_and_the_proxy_one_address(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", args=["--limit", "connections_per_peer=2"])
    with_header = Proxy(relay.port, v1)
    plain = Proxy(relay.port, None)
    held: list[socket.socket] = []
    try:
        for make in (v1, v2):
            s = connect(with_header.port if make is v1 else relay.port, "127.0.0.2")
            held.append(s)
            # Through the proxy (v1), or straight from a client that forges one (v2): no PROXY header is read.
            answer = request(s, prefix=b"" if make is v1 else v2(("10.9.9.9", 1)))
            assert answer is None or answer[0] == 400, answer
            s.close()
        wait_for(lambda: health(relay)["connections"]["tcp"] == 1, 10, what="those two to close")
        # A plain proxy: every client is the proxy's address, the third is over its cap and takes
        # the place of the first client's idle connection.
        for source in ("127.0.0.2", "127.0.0.3", "127.0.0.4"):
            held.append(connect(plain.port, source))
            assert request(held[-1])[0] == 200
        assert request(held[-3]) is None
        h = health(relay)
        assert h["refused"]["peer_cap"] == 1 and h["refused"]["proxy_header"] == 0, h["refused"]
        assert h["proxy"] is None
        assert_clean_log(relay)
    finally:
        for s in held:
            s.close()
        with_header.close()
        plain.close()
        relay.stop()


# --- (c) a trusted proxy's bad or missing header ------------------------------------------------------

def test_malformed_or_missing_header_from_a_trusted_proxy_is_refused_and_counted(tmp_path):
    header_s = 1.5
    relay = RelayProcess(tmp_path / "relay.db", args=["--trusted-proxy", PROXY_ADDR,
                                                      "--limit", f"header_timeout_s={header_s}"])
    proxies = {"bad": Proxy(relay.port, lambda client: b"PROXY TCP4 " + client[0].encode() + b" nonsense\r\n"),
               "v2-bad": Proxy(relay.port, lambda client: v2(client)[:13] + b"\x99" + v2(client)[14:]),
               "none": Proxy(relay.port, None),
               "cut": Proxy(relay.port, lambda client: v1(client)[:12]),
               "good": Proxy(relay.port, v1)}
    held: list[socket.socket] = []
    try:
        for name in ("bad", "v2-bad", "none"):
            held.append(connect(proxies[name].port, "127.0.0.2"))
            assert request(held[-1]) is None, name
        # A proxy that sends half a header, or nothing: closed after header_timeout_s.
        for name in ("cut", "none"):
            held.append(connect(proxies[name].port, "127.0.0.2"))
            took = closed_within(held[-1], header_s + 5)
            assert took is not None and took < header_s + 2, (name, took)
        # A client straight to the relay cannot name an address: its header is HTTP garbage.
        held.append(connect(relay.port, "127.0.0.5"))
        answer = request(held[-1], prefix=v1(("10.9.9.9", 1)))
        assert answer is None or answer[0] == 400, answer
        # And the proxy's well-formed connections are served still.
        held.append(connect(proxies["good"].port, "127.0.0.2"))
        assert request(held[-1])[0] == 200
        h = health(relay)
        assert h["refused"]["proxy_header"] == 5 and h["refused"]["header_timeout"] == 0, h["refused"]
        assert h["proxy"]["proxied"] == 1, h["proxy"]
        log = relay.log.read_text(errors="replace")
        assert f"closing a connection from trusted proxy {PROXY_ADDR}" in log, log[-2000:]
        assert "no complete PROXY header within 1.5 s" in log, log[-2000:]
        assert_clean_log(relay)
    finally:
        for s in held:
            s.close()
        for proxy in proxies.values():
            proxy.close()
        relay.stop()


# --- what aiohttp's handlers see ------------------------------------------------------------------------

def test_handlers_see_the_client_address_and_every_byte_after_the_header():
    async def scenario():
        async def echo(request: web.Request) -> web.Response:
            body = await request.read()
            return web.json_response({"remote": request.remote,
                                      "peername": list(request.transport.get_extra_info("peername")),
                                      "proxy": list(request.transport.get_extra_info("proxy_peername") or ()),
                                      "sha": hashlib.sha256(body).hexdigest(), "n": len(body)})

        guard = ConnGuard(Limits(), Counter(), TrustedProxies.parse(["127.0.0.1"]))
        app = web.Application(middlewares=[guard.middleware])
        app.router.add_post("/echo", echo)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = GuardedSite(runner, "127.0.0.1", free_port(), guard)
        await site.start()
        body = bytes(range(256)) * 300 + b"PROXY TCP4 1.1.1.1 1.1.1.1 1 1\r\n"

        async def post(header: bytes, byte_by_byte: bool = False) -> dict:
            reader, writer = await asyncio.wait_for(asyncio.open_connection("127.0.0.1", site.port), IO_TIMEOUT_S)
            try:
                http = (b"POST /echo HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n"
                        b"Content-Length: %d\r\n\r\n" % len(body)) + body
                if byte_by_byte:  # the header in pieces, as slow networks deliver it
                    for i in range(len(header)):
                        writer.write(header[i:i + 1])
                        await writer.drain()
                        await asyncio.sleep(0.002)
                    writer.write(http)
                else:  # header and request in one segment
                    writer.write(header + http)
                raw = await asyncio.wait_for(reader.read(), IO_TIMEOUT_S)
            finally:
                writer.close()
            head, _, payload = raw.partition(b"\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 200"), raw[:300]
            return json.loads(payload)

        try:
            sha = hashlib.sha256(body).hexdigest()
            got = await post(v1(("192.0.2.7", 40000)))
            assert got["remote"] == "192.0.2.7" and got["peername"] == ["192.0.2.7", 40000], got
            assert got["sha"] == sha and got["n"] == len(body), got
            assert got["proxy"][0] == "127.0.0.1", got  # the proxy's own address stays at hand
            got = await post(v2(("2001:db8::7", 5)), byte_by_byte=True)
            assert got["remote"] == "2001:db8::7" and got["peername"] == ["2001:db8::7", 5, 0, 0] and got["sha"] == sha
            got = await post(v2(None, tlvs=b"\x01\x00\x02h2"))  # LOCAL: the proxy's own address
            assert got["remote"] == "127.0.0.1" and got["proxy"] == [] and got["sha"] == sha
            got = await post(b"PROXY UNKNOWN\r\n")
            assert got["remote"] == "127.0.0.1" and got["sha"] == sha
            assert guard.proxied == 2 and not guard.refused
            for _ in range(100):  # every connection's place given back, under the address it was counted
                if guard.open == 0:
                    break
                await asyncio.sleep(0.05)
            assert guard.open == 0 and not guard._peers
        finally:
            await site.stop()
            await runner.cleanup()

    asyncio.run(asyncio.wait_for(scenario(), 60))
