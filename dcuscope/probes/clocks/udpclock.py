"""The node's side of the light clock exchange over UDP, beside the event stream (its datagrams:
:mod:`dcuscope.protocol.clockdatagram`).

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
import secrets
import socket
import time

from dcuscope.core.clocks import CLOCKS, PretendClock
from dcuscope.protocol.clockdatagram import Tagger, decode_answer, enable_rx_timestamps, encode_request, recv_stamped

BURST = 16
"""Exchanges per report; the minimum-delay filter needs many, most see no queueing at all."""
SPACING_S = 0.02
"""Between the exchanges of a burst: spread over ~0.3 s, clear of one another."""
ANSWER_TIMEOUT_S = 0.25
GIVE_UP_AFTER = 3
"""A burst ends when its first exchanges all went unanswered (UDP blocked, no relay listening)."""


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
