"""Connection limits that hold under TLS (issue 61, item 1): bursts of bare connections from one
address, over TLS and over plain HTTP, against a real relay process. The per-peer cap closes the
longest-idle connection for each newcomer, here often one of the same burst whose TLS handshake has
not even started; every accepted socket must be closed exactly once whatever state it is in, so
that nothing is left in CLOSE-WAIT, ``/api/health`` counts only live connections, and eviction
(at most 16 closing at once) never stalls for good: another address's keep-alive connections are
still served, and its longest idle one still makes room.
"""

from __future__ import annotations

import socket
import ssl
import time

import pytest

from tests.relay.helpers import RelayProcess, get_json, read_http_answer, wait_for
from tests.tlscerts import TestCA

PER_PEER = 16
"""The relay's default connections_per_peer."""
BURST = 40
ATTACKER, NEIGHBOUR = "127.0.0.7", "127.0.0.8"
HEADER_S = 1.0
TCP_STATES = {"01": "ESTABLISHED", "08": "CLOSE_WAIT", "09": "LAST_ACK", "0B": "CLOSING"}
"""The states of a server socket not yet closed by the relay (/proc/net/tcp's hex codes)."""


@pytest.fixture(scope="module", params=["tls", "plain"])
def relay(request, tmp_path_factory):
    """(relay, SSLContext of a client that trusts it, or None over plain HTTP)."""
    tmp = tmp_path_factory.mktemp(request.param)
    args = ["--limit", f"header_timeout_s={HEADER_S}"]
    context = None
    if request.param == "tls":
        ca = TestCA(tmp)
        server = ca.issue("relay")
        args += ["--tls-cert", str(server.cert), "--tls-key", str(server.key)]
        context = ssl.create_default_context(cafile=str(ca.cert))
    proc = RelayProcess(tmp / "relay.db", args=args)
    yield proc, context
    proc.stop()


def held_sockets(port: int) -> dict[str, int]:
    """The relay's sockets on ``port`` that it has not closed, by state (``/proc/net/tcp``)."""
    held: dict[str, int] = {}
    with open("/proc/net/tcp") as table:
        next(table)
        for line in table:
            local, state = line.split()[1], line.split()[3]
            if int(local.split(":")[1], 16) == port and state in TCP_STATES:
                held[TCP_STATES[state]] = held.get(TCP_STATES[state], 0) + 1
    return held


def burst(port: int, first_bytes: bytes) -> list[socket.socket]:
    """``BURST`` connections from ``ATTACKER``, all connected before the relay accepts the first,
    each sending ``first_bytes`` (b"": nothing)."""
    socks = []
    for _ in range(BURST):
        s = socket.socket()
        s.bind((ATTACKER, 0))
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", port))
        socks.append(s)
    for s in socks:
        s.setblocking(True)
        s.settimeout(5)
        if first_bytes:
            try:
                s.sendall(first_bytes)
            except OSError:  # refused or evicted already
                pass
    return socks


def tcp_in_health(relay: RelayProcess, context) -> int:
    """Connections the relay holds, but the one asking."""
    return get_json(f"{relay.url}/api/health", context=context)["connections"]["tcp"] - 1


def keep_alive(relay: RelayProcess, context) -> socket.socket:
    """A connection from ``NEIGHBOUR`` that was served one request and is kept alive, idle."""
    s = socket.create_connection(("127.0.0.1", relay.port), 10, source_address=(NEIGHBOUR, 0))
    if context is not None:
        s = context.wrap_socket(s, server_hostname="127.0.0.1")
    ask(s)
    return s


def ask(s: socket.socket) -> None:
    s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    answer = read_http_answer(s)
    assert answer is not None and answer[0] == 200, answer


def test_bursts_from_one_address_leave_nothing_behind_and_eviction_goes_on(relay):
    relay, context = relay
    # Bare connections (a TLS task that never starts its peek), and ones that start a handshake
    # (0x16) and stall in it: three bursts each, more than the 16 evictions that may run at once.
    for first_bytes in (b"", b"", b"", b"\x16\x03\x01\x02\x00", b"\x16\x03\x01\x02\x00", b"\x16\x03\x01\x02\x00"):
        socks = burst(relay.port, first_bytes)
        time.sleep(0.5)  # not a bound: the relay accepts the whole burst meanwhile, and makes room
        for s in socks:
            s.close()
        wait_for(lambda: not held_sockets(relay.port), 10 + HEADER_S, 0.2,
                 "no server socket left on the relay's port")
        wait_for(lambda: tcp_in_health(relay, context) == 0, 10, 0.2, "/api/health's tcp back to 0")
    health = get_json(f"{relay.url}/api/health", context=context)
    assert health["refused"]["peer_cap"] > 0, health["refused"]

    # Another address: its keep-alive connections are served, and at its cap the longest idle one
    # makes room for the next (not reset, as when the evictions in flight had stalled for good).
    kept = [keep_alive(relay, context) for _ in range(PER_PEER + 1)]
    try:
        kept[0].settimeout(5)
        try:
            assert kept[0].recv(1) == b""  # the longest-idle one made room
        except (ConnectionResetError, ssl.SSLError):  # aborted under TLS
            pass
        for s in kept[1:]:
            ask(s)
    finally:
        for s in kept:
            s.close()
    wait_for(lambda: not held_sockets(relay.port), 10, 0.2, "no server socket left after the neighbour")
    assert "Traceback" not in relay.log.read_text(errors="replace")
