"""Bounds on what one connection may send: message size is the WebSocket's ``max_msg_size``
(:data:`probes.wire.MAX_MESSAGE_BYTES`), rate is this bucket's."""

from __future__ import annotations

import time
from dataclasses import dataclass


@dataclass(frozen=True)
class Limits:
    messages_per_s: float = 2000.0
    message_burst: float = 4000.0
    bytes_per_s: float = 64 * 1024 * 1024
    byte_burst: float = 128 * 1024 * 1024


class TokenBucket:
    """Two token buckets (messages and bytes) refilled continuously; ``take`` never blocks."""

    def __init__(self, limits: Limits) -> None:
        self._limits = limits
        self._messages = limits.message_burst
        self._bytes = limits.byte_burst
        self._at = time.monotonic()

    def take(self, nbytes: int) -> bool:
        """Spend one message of ``nbytes``; False when the connection exceeds its rate."""
        now = time.monotonic()
        dt, self._at = now - self._at, now
        lim = self._limits
        self._messages = min(lim.message_burst, self._messages + dt * lim.messages_per_s)
        self._bytes = min(lim.byte_burst, self._bytes + dt * lim.bytes_per_s)
        if self._messages < 1 or self._bytes < nbytes:
            return False
        self._messages -= 1
        self._bytes -= nbytes
        return True
