"""The PROXY protocol (HAProxy's, v1 text and v2 binary): a client's real address behind a TCP
load balancer or proxy.

Behind a proxy every connection comes from the proxy's address, so the guard's per-address caps
(``connections_per_peer``) would put all nodes and browsers under one cap. A proxy configured to
send the PROXY protocol (HAProxy ``send-proxy``/``send-proxy-v2``, nginx ``proxy_protocol on``,
AWS NLB, ...) starts each connection with a header naming the client; ``dcuscope relay
--trusted-proxy ADDR`` says which peers are such proxies (:class:`TrustedProxies`). Only their
connections are read for a header, and each of them must start with one: anybody else could
otherwise claim any address, and a trusted proxy's connection without a header is a
misconfiguration the operator must hear of, not a client to serve under the proxy's address.

:func:`parse_header` reads a header from the first bytes of a connection, incrementally (None
until it is complete); :class:`~dcuscope.relay.guard.connections.ConnGuard` feeds it, within the
connection's ``header_timeout_s``, before aiohttp sees a byte. What it returns says how many bytes
the header took (the rest is the client's) and the client's address, or None where the header
names none: "PROXY UNKNOWN", a v2 LOCAL command (the proxy's own health checks), a v2 UNSPEC or
UNIX address; the connection then keeps the proxy's address, as the specification asks.

Specification: https://www.haproxy.org/download/2.9/doc/proxy-protocol.txt
"""

from __future__ import annotations

import ipaddress
import struct
from collections.abc import Iterable
from dataclasses import dataclass

V1_PREFIX = b"PROXY "
V1_MAX_BYTES = 107
"""The longest v1 line, "\\r\\n" included (the specification's bound: "PROXY TCP6" and two full
IPv6 addresses and ports)."""
V2_SIGNATURE = b"\r\n\r\n\x00\r\nQUIT\n"
V2_FIXED_BYTES = 16
"""Signature, version and command, family and transport, length (big-endian)."""
V2_LOCAL, V2_PROXY = 0x0, 0x1
V2_INET, V2_INET6 = 0x1, 0x2
V2_ADDRESS_BYTES = {V2_INET: 12, V2_INET6: 36}
"""Source and destination addresses and ports of each family; TLVs may follow, and are skipped."""

Network = ipaddress.IPv4Network | ipaddress.IPv6Network


class ProxyHeaderError(ValueError):
    """The bytes a trusted proxy sent do not start with a valid PROXY header."""


@dataclass(frozen=True)
class ProxyHeader:
    length: int
    """Bytes the header took; what follows is the client's."""
    client: tuple[str, int] | None
    """The client's address and port; None: keep the proxy's (UNKNOWN, LOCAL, UNSPEC, UNIX)."""
    version: int


def parse_header(data: bytes | bytearray) -> ProxyHeader | None:
    """The PROXY header ``data`` starts with; None while ``data`` is a valid but incomplete start of
    one. ProxyHeaderError when it is not one (so a connection sends at most 107 bytes, or one v2
    header, before the guard knows)."""
    start = bytes(data[:len(V2_SIGNATURE)])
    if V2_SIGNATURE.startswith(start) and len(start) < len(V2_SIGNATURE):
        return None  # both signatures may still come ("PROXY " is no prefix of v2's: this is v2 or nothing)
    if start == V2_SIGNATURE:
        return _parse_v2(data)
    if V1_PREFIX.startswith(start[:len(V1_PREFIX)]):
        return _parse_v1(data)
    raise ProxyHeaderError(f"no PROXY header: the connection starts with {start!r}")


def _parse_v1(data: bytes | bytearray) -> ProxyHeader | None:
    newline = data.find(b"\n", 0, V1_MAX_BYTES)
    if newline >= 0 and (newline == 0 or data[newline - 1] != ord("\r")):
        raise ProxyHeaderError("PROXY v1 line ends without CR")  # at once, rather than at 107 bytes
    end = newline - 1 if newline >= 0 else -1
    if end < 0:
        if len(data) >= V1_MAX_BYTES:
            raise ProxyHeaderError(f"PROXY v1 line without CRLF within {V1_MAX_BYTES} bytes")
        if len(data) >= len(V1_PREFIX) and not data.startswith(V1_PREFIX):
            raise ProxyHeaderError("no PROXY header")
        return None
    line = bytes(data[:end])
    try:
        words = line.decode("ascii").split(" ")
    except UnicodeDecodeError:
        raise ProxyHeaderError("PROXY v1 line is not ASCII") from None
    if words[0] != "PROXY" or len(words) < 2:
        raise ProxyHeaderError(f"malformed PROXY v1 line {line[:V1_MAX_BYTES]!r}")
    if words[1] == "UNKNOWN":  # whatever follows is to be ignored
        return ProxyHeader(end + 2, None, 1)
    if words[1] not in ("TCP4", "TCP6") or len(words) != 6:
        raise ProxyHeaderError(f"malformed PROXY v1 line {line!r}")
    kind = ipaddress.IPv4Address if words[1] == "TCP4" else ipaddress.IPv6Address
    try:
        source, _ = kind(words[2]), kind(words[3])
    except ValueError:
        raise ProxyHeaderError(f"PROXY v1 line with a bad {words[1]} address: {line!r}") from None
    port, _ = _port(words[4], line), _port(words[5], line)
    return ProxyHeader(end + 2, (_address(source), port), 1)


def _port(text: str, line: bytes) -> int:
    # Plain decimal, no sign, no spaces, no leading zero: int() alone would take "+80" or "0080".
    if not text.isascii() or not text.isdigit() or len(text) > 5 or (text[0] == "0" and text != "0") \
            or int(text) > 65535:
        raise ProxyHeaderError(f"PROXY v1 line with a bad port: {line!r}")
    return int(text)


def _parse_v2(data: bytes | bytearray) -> ProxyHeader | None:
    if len(data) < V2_FIXED_BYTES:
        return None
    version_command, family_transport, length = struct.unpack_from("!BBH", data, len(V2_SIGNATURE))
    version, command = version_command >> 4, version_command & 0xF
    if version != 2:
        raise ProxyHeaderError(f"PROXY v2 header of version {version}")
    if command not in (V2_LOCAL, V2_PROXY):
        raise ProxyHeaderError(f"PROXY v2 header with unknown command {command}")
    total = V2_FIXED_BYTES + length
    if len(data) < total:
        return None
    family = family_transport >> 4
    if command == V2_LOCAL or family not in V2_ADDRESS_BYTES:  # health checks; UNSPEC, UNIX: no IP to use
        if family > 3:
            raise ProxyHeaderError(f"PROXY v2 header with unknown address family {family}")
        return ProxyHeader(total, None, 2)
    if length < V2_ADDRESS_BYTES[family]:
        raise ProxyHeaderError(f"PROXY v2 header too short for its addresses ({length} bytes)")
    body = bytes(data[V2_FIXED_BYTES:V2_FIXED_BYTES + V2_ADDRESS_BYTES[family]])
    if family == V2_INET:
        source, port = ipaddress.IPv4Address(body[:4]), struct.unpack_from("!H", body, 8)[0]
    else:
        source, port = ipaddress.IPv6Address(body[:16]), struct.unpack_from("!H", body, 32)[0]
    return ProxyHeader(total, (_address(source), port), 2)


def _address(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> str:
    # A proxy listening on IPv6 names an IPv4 client ::ffff:a.b.c.d: one client, one address for the caps.
    mapped = getattr(ip, "ipv4_mapped", None)
    return str(mapped or ip)


class TrustedProxies:
    """The peers whose connections start with a PROXY header (``--trusted-proxy``): addresses and
    networks; empty, none (the relay then never reads a header)."""

    def __init__(self, networks: Iterable[Network] = ()) -> None:
        self.networks: tuple[Network, ...] = tuple(dict.fromkeys(networks))

    @classmethod
    def parse(cls, values: Iterable[str]) -> "TrustedProxies":
        """From ``--trusted-proxy`` values, each ``ADDR[,ADDR...]`` (IP addresses or CIDR networks);
        ValueError names a bad one."""
        networks = []
        for value in values:
            for item in value.split(","):
                item = item.strip()
                if not item:
                    raise ValueError(f"empty address in {value!r}")
                try:
                    networks.append(ipaddress.ip_network(item, strict=True))
                except ValueError as exc:
                    hint = "" if "/" in item else " (an IP address or a network such as 10.0.0.0/8; no host names)"
                    raise ValueError(f"{item!r} is not an IP address or network: {exc}{hint}") from None
        return cls(networks)

    def __bool__(self) -> bool:
        return bool(self.networks)

    def __contains__(self, peer: object) -> bool:
        """Whether ``peer`` (an address string as accept() gives it) is a trusted proxy."""
        if not self.networks or not isinstance(peer, str):
            return False
        try:
            ip = ipaddress.ip_address(peer.split("%", 1)[0])  # an IPv6 scope names no other host
        except ValueError:  # a Unix socket's path, say: no proxy of ours
            return False
        ip = getattr(ip, "ipv4_mapped", None) or ip
        return any(ip in net for net in self.networks)

    def as_list(self) -> list[str]:
        return [str(net) if net.num_addresses > 1 else str(net.network_address) for net in self.networks]
