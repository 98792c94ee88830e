"""Every bound the relay puts on what clients may send or hold, in one place.

:class:`Limits` holds them all, with defaults sized for the paper's load (a DCU ships ~4,300
events/s, about 100 KB/s decompressed) with wide headroom; ``dcuscope relay --limit NAME=VALUE``
sets any of them, ``relay --help`` lists them (:func:`limits_help`) and ``/api/health`` shows
them with the counts of what they refused. The largest WebSocket message is
:data:`dcuscope.protocol.wire.MAX_MESSAGE_BYTES`; the message rate of one connection is :class:`TokenBucket`'s, its
decompressed byte rate (and that of all together) :class:`ByteBucket`'s.
"""

from __future__ import annotations

import ast
import inspect
import textwrap
import time
from dataclasses import dataclass, fields, replace

MIB = 1024 * 1024


@dataclass(frozen=True)
class Limits:
    # --- one ingest connection ---
    messages_per_s: float = 2000.0
    """Messages per second one ingest connection may send (a node sends ~20 batches and 2 syncs a second)."""
    message_burst: float = 4000.0
    """Messages one ingest connection may send at once, above the rate."""
    bytes_per_s: float = 32 * MIB
    """Decompressed bytes per second one ingest connection may send (1.4 M events/s); beyond it the relay
    stops reading from it for a while (back-pressure), it does not close it."""
    byte_burst: float = 64 * MIB
    """Decompressed bytes one ingest connection may send at once, above the rate."""
    hello_timeout_s: float = 5.0
    """Time a new ingest connection has to say hello before it is closed."""
    # --- all clients together ---
    total_bytes_per_s: float = 128 * MIB
    """Decompressed bytes per second of all ingest connections together (back-pressure beyond it)."""
    connections: int = 256
    """Ingest WebSocket connections at once (one per node)."""
    connections_per_peer: int = 16
    """TCP connections at once from one IP address (ingest, API and browsers)."""
    tcp_connections: int = 1024
    """TCP connections at once in all (lowered to fit the process's file descriptor limit)."""
    header_timeout_s: float = 10.0
    """Time a client has to send a complete HTTP request head (slowloris)."""
    keepalive_s: float = 15.0
    """Time an idle HTTP keep-alive connection stays open."""
    # --- what one run may declare and hold ---
    stages: int = 64
    """Stages one run may declare."""
    name_chars: int = 200
    """Characters of a node or stage name."""
    sources: int = 256
    """Distinct source ids one run's events may name."""
    run_mb: float = 64.0
    """Memory one run's live state may hold (open frames, rolling window, recent frames, exact values)."""
    live_mb: float = 256.0
    """Memory all runs' live states may hold together; each run gets an equal share, at most run_mb."""
    silent_s: float = 8.0
    """A connected run silent this long (a node syncs its clock every 2 s) no longer holds its node's name:
    a new run of that name takes over and the old connection is closed; until then a new run is refused."""
    runs_held: int = 64
    """Runs whose live state the relay keeps in memory (ended and superseded runs leave first; they stay stored)."""
    ended_keep_s: float = 60.0
    """How long a run that ended stays among the fleet's live rows (the overview, /api/nodes) before its live state
    leaves memory; it stays stored, in the page's session list and History."""
    # --- values ---
    clock_offset_s: float = 86400.0
    """Largest clock offset (node - relay) a sample or correction may state; beyond, the sample is rejected."""
    clock_rtt_s: float = 10.0
    """Largest round trip of a clock sample; beyond, the sample is rejected."""
    clock_packets_per_s: float = 64.0
    """UDP clock exchanges per second one connection's key may ask for (a node sends 16 every ~2 s); beyond,
    datagrams are dropped unanswered and counted (/api/health clock_udp.rate_key)."""
    total_clock_packets_per_s: float = 4096.0
    """UDP clock exchanges per second of all keys together; beyond, dropped unanswered (clock_udp.rate_total)."""
    # --- the relay's own log ---
    log_repeats_per_min: int = 10
    """Times a minute the same warning or error may be logged; the rest are counted and summarised."""

    def with_values(self, assignments: list[str]) -> "Limits":
        """These limits with ``NAME=VALUE`` assignments applied; ValueError names a bad one."""
        types = {f.name: f.type for f in fields(self)}
        changes = {}
        for item in assignments:
            name, sep, text = item.partition("=")
            name = name.strip().replace("-", "_")
            if not sep or name not in types:
                raise ValueError(f"unknown limit {name!r} (one of {', '.join(types)})")
            try:
                value = int(text) if types[name] in (int, "int") else float(text)
            except ValueError:
                raise ValueError(f"limit {name} must be a number, not {text!r}") from None
            if not value > 0:
                raise ValueError(f"limit {name} must be positive, not {text!r}")
            changes[name] = value
        return replace(self, **changes)

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def limits_help(limits: Limits = Limits()) -> str:
    """The limits, their defaults and meanings, for ``relay --help``."""
    docs = _docs()
    lines = ["limits (--limit NAME=VALUE; counted in /api/health):"]
    for name, value in limits.as_dict().items():
        shown = f"{value / MIB:g} MiB" if name.startswith(("bytes", "byte_", "total_bytes")) else f"{value:g}"
        lines.append(textwrap.fill(f"{name} = {shown}: {docs.get(name, '')}", width=100, initial_indent="  ",
                                   subsequent_indent="      "))
    return "\n".join(lines)


def _docs() -> dict[str, str]:
    """Field docstrings, read from this module's source (one place for the meaning of each limit)."""
    tree = ast.parse(inspect.getsource(Limits))
    body = tree.body[0].body
    docs = {}
    for a, b in zip(body, body[1:]):
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant):
            docs[a.target.id] = " ".join(str(b.value.value).split())
    return docs


class TokenBucket:
    """The message bucket of one connection, refilled continuously; ``take`` never blocks."""

    def __init__(self, limits: Limits) -> None:
        self._limits = limits
        self._messages = limits.message_burst
        self._at = time.monotonic()

    def take(self) -> bool:
        """Spend one message; False when the connection exceeds its message rate."""
        now = time.monotonic()
        dt, self._at = now - self._at, now
        lim = self._limits
        self._messages = min(lim.message_burst, self._messages + dt * lim.messages_per_s)
        if self._messages < 1:
            return False
        self._messages -= 1
        return True


class ByteBucket:
    """Decompressed bytes at ``rate`` per second with ``burst`` at once. ``charge`` always takes the
    bytes, running into debt, and says how long the caller must wait for the debt to be paid: the
    caller stops reading from its connection meanwhile (back-pressure through TCP)."""

    def __init__(self, rate: float, burst: float) -> None:
        self._rate, self._burst = rate, burst
        self._tokens = burst
        self._at = time.monotonic()

    def charge(self, nbytes: int) -> float:
        """Take ``nbytes``; seconds to wait before the next read (0 within the rate)."""
        now = time.monotonic()
        dt, self._at = now - self._at, now
        self._tokens = min(self._burst, self._tokens + dt * self._rate) - nbytes
        return max(0.0, -self._tokens / self._rate)
