"""The light clock exchange over UDP, beside the event stream: its datagrams and the node's side.

The relay's hello reply names ``clock_port`` and a ``clock_key`` (16 random bytes, hex) tied to
that WebSocket connection. The node sends requests to the relay's host on that port and the relay
answers each with its receive and send times; the node reports the completed samples in its
``clock`` message (``"via": "udp"``), where the relay checks each (t2, t3) against the pairs it
answered for that key, as it does for the WebSocket ``sync``. An answer is never larger than its
request (no amplification). Two versions of the datagrams::

    request  magic b"DCUQ", version, 3 zero bytes, key (16), nonce (8)                  [, tag (16)]
    answer   magic b"DCUA", version, 3 zero bytes, nonce (8), t2 (8, signed), t3 (8, signed) [, tag (16)]

Version 1 (32 bytes) is plaintext: the key travels in the clear, so whoever sees a request can
answer it in the relay's place, or alter an answer on its way, and the node takes any answer
whose nonce matches: its offset estimate is only as safe as the path. Version 2 (48 bytes) ends
in a tag, the first 16 bytes of HMAC-SHA256 over the key and the datagram before the tag, made
with ``clock_secret``: 32 random bytes the relay adds to its hello reply only when the WebSocket
runs over TLS, so the secret never travels in the clear nor in a datagram. A node given a secret
sends version 2 and takes only version 2 answers whose tag is right (the others are counted in
``forged``); the relay answers a key that has a secret only in version 2, and still answers a
version 1 request for a key without one (a node that got no secret: no TLS, an older node).

Both ends take their receive time from the kernel (``SO_TIMESTAMPNS``: CLOCK_REALTIME when the
datagram arrived, not when Python read it) and read their send time just before ``sendto``:
t1 node send, t2 relay kernel receive, t3 relay send, t4 node kernel receive. The relay's tag
over t3 is made after t3 is read, before ``sendto`` (under a microsecond, with the HMAC keyed
once per connection). The node's two times are moved to the probes' clock (tai, monotonic: the
difference to CLOCK_REALTIME read at each receipt) and through its
:class:`~dcuscope.core.clocks.PretendClock`, as its events are.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import secrets
import socket
import struct
import time
from typing import NamedTuple

from dcuscope.core.clocks import CLOCKS, PretendClock

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
BURST = 16
"""Exchanges per report; the minimum-delay filter needs many, most see no queueing at all."""
SPACING_S = 0.02
"""Between the exchanges of a burst: spread over ~0.3 s, clear of one another."""
ANSWER_TIMEOUT_S = 0.25
GIVE_UP_AFTER = 3
"""A burst ends when its first exchanges all went unanswered (UDP blocked, no relay listening)."""


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


class UdpClock:
    """The node's end of the exchange with one relay connection (``key``; with ``secret``, tagged)."""

    def __init__(self, sock: socket.socket, key: bytes, pretend: PretendClock, secret: bytes | None = None) -> None:
        self._sock, self._key, self._pretend = sock, key, pretend
        self._tagger = Tagger(secret, key) if secret is not None else None
        self.forged = 0
        """Answers refused for a wrong or missing tag: forged, or altered on the way."""
        self._realtime = pretend.clock_id == CLOCKS["realtime"]
        self._waiting: dict[int, asyncio.Future] = {}
        self.refused = False
        """The relay's host said nothing listens there (ICMP port unreachable)."""
        asyncio.get_running_loop().add_reader(sock.fileno(), self._readable)

    @classmethod
    async def open(cls, host: str, port: int, key: bytes, pretend: PretendClock,
                   secret: bytes | None = None) -> "UdpClock":
        """Raises OSError when ``host`` cannot be resolved or reached."""
        loop = asyncio.get_running_loop()
        family, _, _, _, addr = (await loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM))[0]
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            enable_rx_timestamps(sock)
            sock.connect(addr)  # answers from anyone but the relay's address are not even read
        except OSError:
            sock.close()
            raise
        return cls(sock, key, pretend, secret)

    def close(self) -> None:
        with contextlib.suppress(ValueError, OSError):
            asyncio.get_running_loop().remove_reader(self._sock.fileno())
        self._sock.close()
        for waiter in self._waiting.values():
            waiter.cancel()

    async def burst(self, count: int = BURST, spacing_s: float = SPACING_S,
                    timeout_s: float = ANSWER_TIMEOUT_S) -> list[list[int]]:
        """Completed samples [t1, t2, t3, t4] of up to ``count`` exchanges (none if no answer came)."""
        samples: list[list[int]] = []
        for i in range(count):
            if i == GIVE_UP_AFTER and not samples or self.refused:
                break
            sample = await self._exchange(timeout_s)
            if sample is not None:
                samples.append(sample)
            await asyncio.sleep(spacing_s)
        return samples

    async def _exchange(self, timeout_s: float) -> list[int] | None:
        nonce = secrets.randbits(64)
        waiter = asyncio.get_running_loop().create_future()
        self._waiting[nonce] = waiter
        try:
            packet = encode_request(self._key, nonce, self._tagger)
            t1 = self._pretend.now()
            self._sock.send(packet)
            t2, t3, t4 = await asyncio.wait_for(waiter, timeout_s)
            return [t1, t2, t3, t4]
        except ConnectionRefusedError:
            self.refused = True
            return None
        except (OSError, asyncio.TimeoutError):
            return None
        finally:
            self._waiting.pop(nonce, None)

    def _readable(self) -> None:
        while True:
            try:
                data, _, rx_ns, truncated = recv_stamped(self._sock)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:
                self.refused = True
                return
            except OSError:
                return
            answer = None if truncated else decode_answer(data)
            if answer is None:
                continue
            if self._tagger is None:
                if answer.tagged:  # nothing to check it with: only a relay that gave no secret is heard
                    continue
            elif not (answer.tagged and self._tagger.check(data)):
                self.forged += 1
                continue
            waiter = self._waiting.get(answer.nonce)
            if waiter is not None and not waiter.done():
                waiter.set_result((answer.t2, answer.t3, self._pretend.of(self._to_clock(rx_ns))))

    def _to_clock(self, realtime_ns: int) -> int:
        """A CLOCK_REALTIME kernel time on the probes' clock: the two clocks' difference, read
        around one CLOCK_REALTIME reading so that the reads' own cost cancels, the tightest of
        DIFFERENCE_READS brackets (a thread preempted inside one would skew it by half the pause)."""
        if self._realtime:
            return realtime_ns
        return realtime_ns + clock_difference_ns(self._pretend.clock_id)


DIFFERENCE_READS = 3


def clock_difference_ns(clock_id: int, reads: int = DIFFERENCE_READS) -> int:
    """``clock_id``'s time minus CLOCK_REALTIME's, ns: of ``reads`` brackets of a CLOCK_REALTIME
    reading between two of ``clock_id``, the tightest one's."""
    best = None
    for _ in range(reads):
        before = time.clock_gettime_ns(clock_id)
        real = time.time_ns()
        after = time.clock_gettime_ns(clock_id)
        if best is None or after - before < best[0]:
            best = (after - before, (before + after) // 2 - real)
    return best[1]
