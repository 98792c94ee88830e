"""Cut one TCP path as a real fault does: a process in a network namespace of its own, joined to the
host by one veth pair, and iptables rules *inside* that namespace that black-hole one port (DROP, no
reset: established connections stall, new ones get no answer).

The host is the hub: a namespace reaches the host's end of its veth pair and nothing else (no default
route, and the host forwards no packets: tests never turn IP forwarding on). A server a namespaced
process talks to listens on the host's end (``PostgresServer(listen=[ns.host_addr])``, a relay with
``--host ns.host_addr``); one in another namespace is reached through a :class:`Forward` on the host.

    with Namespace() as ns:
        pg = PostgresServer(listen=[ns.host_addr]).start()
        relay = RelayProcess(pg.new_database(ns.host_addr), log=LOG, prefix=ns.prefix,
                             args=["--host", ns.ns_addr])  # relay.url: http://NS_ADDR:PORT
        ns.drop(pg.port)  # the relay's store is cut off
        ns.restore()

Nothing here touches the host's firewall, routes (beyond the connected /30 of a veth's host end, gone
with it) or clock. Each namespace has a unique name and a /30 of 10.128.0.0/10 picked from the process
id and a counter, skipping any the host routes already (tests/ptpnet.py uses 10.77.0.0/24, inside its
namespaces only). :meth:`Namespace.close` removes the veth pair and the namespace, its rules with it,
whatever happened; it ends no process: those started in the namespace are their owner's to stop.
"""

from __future__ import annotations

import ipaddress
import itertools
import os
import random
import re
import socket
import subprocess
import threading

from tests.ptpnet import netns_permitted

__all__ = ["Forward", "Namespace", "netns_permitted"]

POOL = ipaddress.ip_network("10.128.0.0/10")
"""Where namespaces' /30s are taken from: 2**20 of them, 64 per process id (modulo 2**14)."""
_turn = itertools.count()


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if check and done.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)} failed: {done.stderr.strip()}")
    return done


def _routed() -> list[ipaddress.IPv4Network]:
    """The IPv4 networks the host has addresses in or routes to."""
    text = _ip("-4", "-o", "addr").stdout + _ip("-4", "route", "show", "table", "all").stdout
    return [ipaddress.ip_network(cidr, strict=False) for cidr in re.findall(r"\b\d+\.\d+\.\d+\.\d+/\d+\b", text)]


def _free_network() -> ipaddress.IPv4Network:
    routed = _routed()
    base = int(POOL.network_address) + ((os.getpid() & 0x3FFF) << 8)
    for _ in range(64):
        net = ipaddress.ip_network((base + 4 * (next(_turn) & 0x3F), 30))
        if not any(net.overlaps(other) for other in routed):
            return net
    raise RuntimeError(f"no free /30 left for process {os.getpid()} in {POOL}")


class Namespace:
    """A network namespace joined to the host by one veth pair: ``host_addr`` on the host's end,
    ``ns_addr`` inside, both in ``network`` (a /30); ``prefix`` runs a command inside
    (``[*ns.prefix, *argv]``); ``name`` is the namespace's."""

    def __init__(self) -> None:
        # veth names have 15 characters at most: these have 15
        tag = f"nsn{os.getpid() % 100000:05d}{next(_turn) % 4096:03x}{random.randrange(256):02x}"
        self.name = tag
        self._host_if, self._ns_if = f"{tag}h", f"{tag}n"
        self.network = _free_network()
        host, inside = self.network.hosts()
        self.host_addr, self.ns_addr = str(host), str(inside)
        self.prefix = ["ip", "netns", "exec", self.name]
        self._rules: list[list[str]] = []
        self._made: list[str] = []

    def __enter__(self) -> Namespace:
        try:
            _ip("netns", "add", self.name)
            self._made.append("netns")
            _ip("link", "add", self._host_if, "type", "veth", "peer", "name", self._ns_if, "netns", self.name)
            self._made.append("veth")
            _ip("addr", "add", f"{self.host_addr}/30", "dev", self._host_if)
            _ip("link", "set", self._host_if, "up")
            _ip("-n", self.name, "addr", "add", f"{self.ns_addr}/30", "dev", self._ns_if)
            _ip("-n", self.name, "link", "set", self._ns_if, "up")
            _ip("-n", self.name, "link", "set", "lo", "up")
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def run(self, *argv: str, timeout: float = 20) -> subprocess.CompletedProcess:
        """``argv`` inside the namespace, to its end; its output as text."""
        return subprocess.run([*self.prefix, *argv], capture_output=True, text=True, timeout=timeout)

    def _iptables(self, *args: str) -> str:
        done = self.run("iptables", "-w", *args)
        if done.returncode != 0:
            raise RuntimeError(f"iptables {' '.join(args)} in {self.name} failed: {done.stderr.strip()}")
        return done.stdout

    def drop(self, port: int, *, dport: bool = True) -> None:
        """Black-hole TCP port ``port`` inside the namespace until :meth:`restore`. With ``dport``, the
        port of a server outside (the host's PostgreSQL): what goes out to it and what comes back from
        it; without, the port of a server inside (a relay listening here): what comes in to it and what
        goes out from it. Nothing answers: connections stall, new ones are never accepted."""
        out, back = ("--dport", "--sport") if dport else ("--sport", "--dport")
        for rule in (["OUTPUT", "-p", "tcp", out, str(port), "-j", "DROP"],
                     ["INPUT", "-p", "tcp", back, str(port), "-j", "DROP"]):
            self._iptables("-I", *rule)
            self._rules.append(rule)

    def restore(self) -> None:
        """Remove every rule :meth:`drop` added."""
        while self._rules:
            self._iptables("-D", *self._rules[-1])
            self._rules.pop()

    def dropped(self) -> int:
        """Packets the rules of :meth:`drop` have dropped so far (the namespace has no others)."""
        rows = self._iptables("-L", "-n", "-v", "-x").splitlines()
        return sum(int(row.split()[0]) for row in rows if row.split()[2:3] == ["DROP"])

    def close(self) -> None:
        """Remove the veth pair and the namespace (its rules with it); idempotent. Deleting the host's
        end takes the pair at once, even while processes left running keep the namespace itself alive."""
        if "veth" in self._made:
            _ip("link", "del", self._host_if, check=False)
        if "netns" in self._made:
            _ip("netns", "del", self.name, check=False)
        self._made.clear()
        self._rules.clear()


class Forward:
    """TCP from ``listen`` (a host address and port, say a namespace's ``host_addr``) passed on to
    ``target``, by a thread on the host: how a process in one namespace reaches a server in another
    without the host forwarding packets. A connection whose target is unreachable is closed."""

    def __init__(self, listen: tuple[str, int], target: tuple[str, int]) -> None:
        self.target = target
        self._server = socket.create_server(listen)
        self._server.settimeout(0.2)
        self._open = True
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def __enter__(self) -> Forward:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _accept(self) -> None:
        while self._open:
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            client.settimeout(None)
            try:
                upstream = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            upstream.settimeout(None)
            for src, dst in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(src, dst), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        for sock in (src, dst):  # shutdown wakes the other direction's recv; close alone would not
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def close(self) -> None:
        """Stop accepting (connections open now end with their peers)."""
        self._open = False
        self._thread.join(5)
        self._server.close()
