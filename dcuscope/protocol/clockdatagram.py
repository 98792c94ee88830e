"""The clock exchange's datagrams over UDP, beside the event stream: what node and relay send.

The relay's hello reply offers the exchange (``clock_port``, ``clock_key``, over TLS also
``clock_secret``: :func:`parse_offer`); the node sends requests to that port and the relay answers
each with its receive and send times. An answer is never larger than its request (no
amplification). Two versions of the datagrams::

    request  magic b"DCUQ", version, 3 zero bytes, key (16), nonce (8)                  [, tag (16)]
    answer   magic b"DCUA", version, 3 zero bytes, nonce (8), t2 (8, signed), t3 (8, signed) [, tag (16)]

Version 1 (32 bytes) is plaintext: the key travels in the clear, so whoever sees a request can
answer it in the relay's place, or alter an answer on its way. Version 2 (48 bytes) ends in a tag,
the first 16 bytes of HMAC-SHA256 over the key and the datagram before the tag, made with
``clock_secret``: 32 random bytes the relay adds to its hello reply only when the WebSocket runs
over TLS, so the secret never travels in the clear nor in a datagram. Both ends take their receive
time from the kernel (``SO_TIMESTAMPNS``, :func:`enable_rx_timestamps`, :func:`recv_stamped`).

The node's side of the exchange is :mod:`dcuscope.probes.clocks.udpclock`, the relay's
:mod:`dcuscope.relay.clock.udp`.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import socket
import struct
import time
from typing import NamedTuple

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
"""Linux's value (SO_TIMESTAMPNS_OLD, also SCM_TIMESTAMPNS); Python's socket module lacks it."""
TIMESPEC = struct.Struct("@qq")
VERSION = 1
"""Plaintext datagrams: the key alone says whose request it is."""
VERSION_TAGGED = 2
"""Datagrams that end in a tag made with the connection's secret."""
REQUEST = struct.Struct("<4sB3x16sQ")
ANSWER = struct.Struct("<4sB3xQqq")
REQUEST_MAGIC, ANSWER_MAGIC = b"DCUQ", b"DCUA"
DATAGRAM_BYTES = REQUEST.size
assert REQUEST.size == ANSWER.size == 32
KEY_BYTES = 16
SECRET_BYTES = 32
TAG_BYTES = 16
"""HMAC-SHA256 cut to 128 bits: a forger must guess it afresh for every answer."""
RECV_BYTES = 2048
"""Read buffer: a longer datagram is seen as truncated (MSG_TRUNC) and dropped as oversize."""


class Tagger:
    """Tags of one connection's datagrams: HMAC-SHA256 keyed with its secret, over its key and the
    datagram's first 32 bytes. Keyed once, so that a tag costs one copy and one block."""

    def __init__(self, secret: bytes, key: bytes) -> None:
        self._keyed = hmac.new(secret, key, hashlib.sha256)

    def tag(self, body: bytes) -> bytes:
        mac = self._keyed.copy()
        mac.update(body)
        return mac.digest()[:TAG_BYTES]

    def check(self, data: bytes) -> bool:
        """Whether a version 2 datagram's tag is this connection's."""
        return hmac.compare_digest(self.tag(data[:DATAGRAM_BYTES]), data[DATAGRAM_BYTES:])


class Request(NamedTuple):
    key: bytes
    nonce: int
    tagged: bool


class Answer(NamedTuple):
    nonce: int
    t2: int
    t3: int
    tagged: bool


def _version(data: bytes) -> int | None:
    """The version a datagram's size and version byte agree on, else None."""
    if len(data) == DATAGRAM_BYTES and data[4] == VERSION:
        return VERSION
    if len(data) == DATAGRAM_BYTES + TAG_BYTES and data[4] == VERSION_TAGGED:
        return VERSION_TAGGED
    return None


def encode_request(key: bytes, nonce: int, tagger: Tagger | None = None) -> bytes:
    if tagger is None:
        return REQUEST.pack(REQUEST_MAGIC, VERSION, key, nonce)
    body = REQUEST.pack(REQUEST_MAGIC, VERSION_TAGGED, key, nonce)
    return body + tagger.tag(body)


def decode_request(data: bytes) -> Request | None:
    """A well-formed request of either version (its tag not checked yet), else None."""
    version = _version(data)
    if version is None:
        return None
    magic, _, key, nonce = REQUEST.unpack_from(data)
    return Request(key, nonce, version == VERSION_TAGGED) if magic == REQUEST_MAGIC else None


def encode_answer(nonce: int, t2: int, t3: int, tagger: Tagger | None = None) -> bytes:
    if tagger is None:
        return ANSWER.pack(ANSWER_MAGIC, VERSION, nonce, t2, t3)
    body = ANSWER.pack(ANSWER_MAGIC, VERSION_TAGGED, nonce, t2, t3)
    return body + tagger.tag(body)


def decode_answer(data: bytes) -> Answer | None:
    """A well-formed answer of either version (its tag not checked yet), else None."""
    version = _version(data)
    if version is None:
        return None
    magic, _, nonce, t2, t3 = ANSWER.unpack_from(data)
    return Answer(nonce, t2, t3, version == VERSION_TAGGED) if magic == ANSWER_MAGIC else None


def enable_rx_timestamps(sock: socket.socket) -> None:
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)


def recv_stamped(sock: socket.socket) -> tuple[bytes, object, int, bool]:
    """One datagram: (data, sender, kernel receive time in CLOCK_REALTIME ns, truncated).
    Without a kernel timestamp (never on Linux once enabled) the time of reading stands in."""
    data, ancillary, flags, sender = sock.recvmsg(RECV_BYTES, socket.CMSG_SPACE(TIMESPEC.size))
    stamp = None
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(payload) >= TIMESPEC.size:
            sec, nsec = TIMESPEC.unpack_from(payload)
            stamp = sec * 1_000_000_000 + nsec
    if stamp is None:
        stamp = time.time_ns()
    return data, sender, stamp, bool(flags & socket.MSG_TRUNC)


def new_key() -> bytes:
    return secrets.token_bytes(KEY_BYTES)


def new_secret() -> bytes:
    return secrets.token_bytes(SECRET_BYTES)


class Offer(NamedTuple):
    """The UDP exchange a relay offered on one connection."""
    port: int
    key: bytes
    secret: bytes | None
    """Given over TLS only: then every datagram is tagged."""


def parse_offer(reply: dict) -> Offer | None:
    """The offer in a hello reply, else None (an older relay, or one started with --clock-port 0).
    A malformed ``clock_secret`` voids the offer: falling back to plaintext would drop the tags."""
    port, key, secret = reply.get("clock_port"), reply.get("clock_key"), reply.get("clock_secret")
    if not (isinstance(port, int) and not isinstance(port, bool) and 0 < port < 65536 and isinstance(key, str)):
        return None
    try:
        raw = bytes.fromhex(key)
        raw_secret = None if secret is None else bytes.fromhex(secret)
    except (ValueError, TypeError):
        return None
    if len(raw) != KEY_BYTES or raw_secret is not None and len(raw_secret) != SECRET_BYTES:
        return None
    return Offer(port, raw, raw_secret)
