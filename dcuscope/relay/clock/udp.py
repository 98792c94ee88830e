"""The relay's end of the UDP clock exchange (datagrams: :mod:`dcuscope.protocol.clockdatagram`).

Each ingest connection that said hello gets a random key (``register``), and over TLS a secret
too; a request carrying a key the relay handed out is answered with (t2, t3): t2 the kernel's
receive time (``SO_TIMESTAMPNS``), t3 read just before the answer is tagged and sent. The pair
is remembered in that connection's ``syncs``, where the ingest checks the samples its node
reports (each pair counts once, a bounded number kept). Anything else is dropped unanswered and
counted: a datagram of the wrong size or shape (``malformed``, ``oversize``), an unknown key
(``unknown_key``), a key with a secret whose request has a wrong or no tag, or a tagged request
for a key without one (``bad_tag``), one whose nonce was already answered for its key
(``replayed``), one beyond its key's rate (``Limits.clock_packets_per_s``) or beyond all keys'
rate together (``Limits.total_clock_packets_per_s``). An answer is never larger than its
request, and has the request's version.

Replays are dropped before they reach a rate bucket, so that a bystander who copies a node's
genuine request cannot spend that node's budget with it: each key remembers the nonces it
answered in the last ``REPLAY_WINDOW_S`` (a node draws 64 random bits per request, so its own
never meet). What this does not stop: over a plain (untagged) connection the key travels in the
clear, and whoever sees one request can forge others with fresh nonces, each answered and taken
from the key's bucket as the node's are; and a request captured more than ``REPLAY_WINDOW_S``
ago is answered once more, so a bystander holding many old requests of one connection can still
spend part of its budget (a request carries no counter or time that would say how old it is).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import time
from collections import Counter, OrderedDict

from dcuscope.protocol.clockdatagram import Tagger, decode_request, enable_rx_timestamps, encode_answer, new_key, recv_stamped
from dcuscope.relay.guard.limits import Limits

READS_PER_WAKE = 256
"""Datagrams read per readiness callback: a flood cannot hold the event loop for longer; the
kernel drops what its socket buffer cannot hold."""
REPLAY_WINDOW_S = 30.0
"""How long a key remembers the nonces it answered: a copy of a request within it is dropped as
``replayed``. A node's 8 exchanges a second leave ~240 nonces per key; at most its rate's worth
(``Limits.clock_packets_per_s`` x (REPLAY_WINDOW_S + 1)) can be answered within it, and so kept."""
COUNTS = ("answered", "malformed", "oversize", "unknown_key", "bad_tag", "replayed", "rate_key", "rate_total")

log = logging.getLogger(__name__)


class PacketBucket:
    """``rate`` packets per second, one second's worth at once; ``take`` never blocks."""

    def __init__(self, rate: float) -> None:
        self._rate = rate
        self._tokens = rate
        self._at = time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self._tokens = min(self._rate, self._tokens + (now - self._at) * self._rate)
        self._at = now
        if self._tokens < 1:
            return False
        self._tokens -= 1
        return True


class NonceWindow:
    """The nonces answered in the last ``window_s`` seconds, at most ``most`` of them (the oldest
    forgotten first). Time, not a count alone, decides what is forgotten: a count would let whoever
    holds more old requests than it keeps replay them in turn, each one pushing out the next."""

    __slots__ = ("_window_s", "_most", "_at")

    def __init__(self, window_s: float, most: int) -> None:
        self._window_s, self._most = window_s, most
        self._at: OrderedDict[int, float] = OrderedDict()

    def __len__(self) -> int:
        return len(self._at)

    def seen(self, nonce: int, now: float) -> bool:
        """Whether ``nonce`` was answered within the window (``now``: ``time.monotonic()``)."""
        at, since = self._at, now - self._window_s
        while at and next(iter(at.values())) < since:
            at.popitem(last=False)
        return nonce in at

    def add(self, nonce: int, now: float) -> None:
        self._at[nonce] = now
        if len(self._at) > self._most:
            self._at.popitem(last=False)


class _Key:
    __slots__ = ("syncs", "bucket", "tagger", "nonces")

    def __init__(self, syncs: dict[tuple[int, int], None], rate: float, tagger: Tagger | None) -> None:
        self.syncs, self.bucket, self.tagger = syncs, PacketBucket(rate), tagger
        # The bucket answers at most rate x (window + 1) within a window: a bound never reached.
        self.nonces = NonceWindow(REPLAY_WINDOW_S, math.ceil(rate * (REPLAY_WINDOW_S + 1)))


class ClockUdp:
    """The UDP socket and the keys of the connections that may use it."""

    def __init__(self, limits: Limits, syncs_kept: int) -> None:
        self._limits, self._kept = limits, syncs_kept
        self._keys: dict[bytes, _Key] = {}
        self._total = PacketBucket(limits.total_clock_packets_per_s)
        self._sock: socket.socket | None = None
        self.port = 0
        self.counts: Counter = Counter({name: 0 for name in COUNTS})

    def start(self, host: str, port: int) -> int:
        """Listen on ``host:port`` (0: any free port); the port. OSError if it cannot."""
        family, _, _, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM, flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            enable_rx_timestamps(sock)
            sock.bind(addr)
        except OSError:
            sock.close()
            raise
        self._sock, self.port = sock, sock.getsockname()[1]
        asyncio.get_running_loop().add_reader(sock.fileno(), self._readable)
        return self.port

    def stop(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(ValueError, OSError):
                asyncio.get_running_loop().remove_reader(self._sock.fileno())
            self._sock.close()
            self._sock = None

    def register(self, syncs: dict[tuple[int, int], None], secret: bytes | None = None) -> bytes:
        """A new key whose answers are remembered in ``syncs`` (one connection's); with
        ``secret``, only tagged requests are answered, tagged."""
        key = new_key()
        tagger = Tagger(secret, key) if secret is not None else None
        self._keys[key] = _Key(syncs, self._limits.clock_packets_per_s, tagger)
        return key

    def forget(self, key: bytes) -> None:
        self._keys.pop(key, None)

    @property
    def keys(self) -> int:
        return len(self._keys)

    def _readable(self) -> None:
        sock = self._sock
        for _ in range(READS_PER_WAKE):
            if sock is None:
                return
            try:
                data, sender, t2, truncated = recv_stamped(sock)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # an ICMP error queued by an earlier answer: nothing to do with this one
                continue
            self._take(sock, data, sender, t2, truncated)

    def _take(self, sock: socket.socket, data: bytes, sender: object, t2: int, truncated: bool) -> None:
        if truncated:
            self.counts["oversize"] += 1
            return
        request = decode_request(data)
        if request is None:
            self.counts["malformed"] += 1
            return
        entry = self._keys.get(request.key)
        if entry is None:
            self.counts["unknown_key"] += 1
            return
        tagger = entry.tagger
        if request.tagged != (tagger is not None) or tagger is not None and not tagger.check(data):
            self.counts["bad_tag"] += 1
            return
        now = time.monotonic()
        if entry.nonces.seen(request.nonce, now):  # before the buckets: a replay costs the node nothing
            self.counts["replayed"] += 1
            return
        if not entry.bucket.take():
            self.counts["rate_key"] += 1
            return
        if not self._total.take():
            self.counts["rate_total"] += 1
            return
        entry.nonces.add(request.nonce, now)
        t3 = time.time_ns()
        try:
            sock.sendto(encode_answer(request.nonce, t2, t3, tagger), sender)
        except OSError:  # the node's socket went away: its pair is never reported
            return
        entry.syncs[(t2, t3)] = None
        if len(entry.syncs) > self._kept:
            del entry.syncs[next(iter(entry.syncs))]
        self.counts["answered"] += 1
