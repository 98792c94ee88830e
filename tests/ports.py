"""Ports for the servers that tests start (relays, RTSP servers, demos, Prometheus).

Picking a port by binding port 0 and closing it races when tests run in parallel workers: the
kernel may hand the same number to another worker, or to an outgoing connection, before the
server binds it. Instead each pytest-xdist worker takes its own block of ports below Linux's
ephemeral range (32768 and up by default, where outgoing connections and servers bound to
port 0 get theirs), and hands them out in turn. A port is checked free for both TCP and UDP,
since a relay listens on the same number for its clock exchanges.
"""

from __future__ import annotations

import itertools
import os
import socket

FIRST_PORT = 12000
BLOCK = 600
"""Ports per worker: 20 workers fit below 24000, well under the ephemeral range."""

_turn = itertools.count()


def worker_index() -> int:
    """0 for ``gw0`` (or no xdist), 1 for ``gw1``, ..."""
    name = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    return int(name[2:]) if name.startswith("gw") and name[2:].isdigit() else 0


def free_port(host: str = "127.0.0.1") -> int:
    """A port of this worker's block that nothing listens on now, TCP or UDP; never the same one
    twice in a worker (until the block wraps round)."""
    start = FIRST_PORT + worker_index() * BLOCK
    for _ in range(BLOCK):
        port = start + next(_turn) % BLOCK
        if _bindable(host, port, socket.SOCK_STREAM) and _bindable(host, port, socket.SOCK_DGRAM):
            return port
    raise RuntimeError(f"no free port in {start}..{start + BLOCK - 1} on {host}")


def _bindable(host: str, port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as probe:
        if kind == socket.SOCK_STREAM:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers bind: TIME_WAIT is no obstacle
        try:
            probe.bind((host, port))
        except OSError:
            return False
        return True
