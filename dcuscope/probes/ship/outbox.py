"""The batches of one run on their way to a relay (:class:`Outbox`): events the caller writes, cut
into numbered batches (:mod:`dcuscope.protocol.wire`), each kept until a relay acknowledges it (after
its database committed it).

Batching (adaptive, as Nagle's algorithm): while the link is idle (connected, no batch waiting
for its acknowledgement, none queued to send), what is pending is cut and sent at once, but at
most once per ``min_flush_s`` after the last cut, so that a pipeline writing a few events at a
time does not send a batch per write. While batches are in flight, events gather until the link
is idle again (the last acknowledgement came: it includes the relay's commit), ``batch_events``
are pending, or the oldest pending event has waited ``flush_interval_s``. A paced node thus
ships within a few ms of a write, each batch holding what came during the last round trip; under
bulk load the link is always busy and batches stay ``batch_events`` long. ``adaptive=False``
cuts every ``flush_interval_s`` or at ``batch_events`` whatever the link does (the behaviour
before, which benchmarks/bench_relay.py measures beside it).

Bounds: the buffer of unacknowledged events is bounded (``max_buffer_events``); beyond it the
oldest batches are dropped and counted as ``lost``, a count the relay receives with the next
``hello``/``clock`` message and with ``end`` (with the lowest batch still held, the ``floor``, so
that the relay stops waiting for the dropped ones). A dropped batch that was sent may have been
stored (its acknowledgement lost with the connection, or still to come): it is *doubtful* until
its acknowledgement arrives or the relay is asked (``doubt`` in hello and clock reports; the reply
says which it stored); then it counts delivered or lost. The floor stays at the first doubtful
batch meanwhile.

With a spool (:mod:`dcuscope.probes.ship.spool`), every batch is on disk from its cut until acknowledged:
the bound then holds only the batches kept in memory too; beyond it the oldest are read back
from disk when their turn comes, and nothing is lost until the spool's own bound drops them.

A batch the relay could not store holds all sending for a while (the time the relay asks,
``retry_ms``, growing while failures go on, capped), then goes again.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import OrderedDict, deque
from typing import Callable

import numpy as np

from dcuscope.core.clocks import NEVER
from dcuscope.probes.ship.aio import seconds, wait_event
from dcuscope.probes.ship.relaylink import asked_retry_ms
from dcuscope.probes.ship.runspool import RunSpool
from dcuscope.probes.ship.spoolfile import SpoolError
from dcuscope.protocol.events import EVENT_DTYPE
from dcuscope.protocol.wire import MAX_BATCH_EVENTS, MAX_DOUBT, encode_batch

DEFAULT_BATCH_EVENTS = 8192
DEFAULT_FLUSH_INTERVAL_S = 0.05
"""The longest an event is held on the node before it is cut into a batch (``adaptive=False``:
the period of the cuts)."""
DEFAULT_MIN_FLUSH_S = 0.04
"""Adaptive batching: the shortest time between two cuts that an idle link triggers. A relay's
work per batch (decode, commit, acknowledgement, a pairing merge) is most of its cost at a DCU's
pace: 40 ms instead of 10 holds a paced DCU to 25 batches a second, which took the relay's CPU
per event from 19.7 to 13.4 µs (8 DCUs, docs/benchmarks-log.md, issue 31) for about 20 ms more lag."""
DEFAULT_MAX_BUFFER_EVENTS = 2_000_000
"""About 46 MiB, 7.7 minutes of a paper-sized DCU (4,300 events/s)."""
DEFAULT_WINDOW = 64
"""Batches in flight (sent, not acknowledged) on one connection."""

log = logging.getLogger(__name__)


class Outbox:
    """Batches of run ``run_id``. :meth:`put` is the caller's (any thread, a short lock); every
    other method belongs to the exporter's loop thread."""

    def __init__(self, run_id: str, *, compress: bool = False, batch_events: int = DEFAULT_BATCH_EVENTS,
                 flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S, adaptive: bool = True,
                 min_flush_s: float = DEFAULT_MIN_FLUSH_S, max_buffer_events: int = DEFAULT_MAX_BUFFER_EVENTS,
                 window: int = DEFAULT_WINDOW, backoff_s: tuple[float, float] = (0.1, 5.0),
                 spool: RunSpool | None = None) -> None:
        self.run_id, self._compress = run_id, compress
        self.spool = spool
        self.batch_events = max(1, min(int(batch_events), MAX_BATCH_EVENTS))
        self.flush_interval_s, self.adaptive, self._min_flush = flush_interval_s, adaptive, min_flush_s
        self._max_events = int(max_buffer_events)
        self._window = max(1, int(window))
        self._backoff = backoff_s

        # Shared with the caller's thread: only these, under the lock.
        self._lock = threading.Lock()
        self._pending: list[np.ndarray] = []
        self.pending_n = 0
        self._pending_since = 0.0  # monotonic time of the oldest pending write
        self.shed = 0  # events refused by put because even the pending list was full
        self.written = 0

        # The loop thread's.
        self.unacked: OrderedDict[int, tuple[bytes | None, int]] = OrderedDict()
        """seq -> (the batch, or None where only the spool holds it; its events)."""
        self.unacked_n = 0
        self._memory: OrderedDict[int, int] = OrderedDict()
        """Unacknowledged batches whose bytes are in memory: seq -> events."""
        self._memory_n = 0
        self.inflight: dict[int, float] = {}
        self._tried: set[int] = set()
        """Unacknowledged batches sent at least once (on any connection)."""
        self.doubtful: OrderedDict[int, int] = OrderedDict()
        """Evicted batches that were sent: seq -> events (module doc)."""
        self.to_send: deque[int] = deque()
        self.next_seq = 0
        self._last_cut = NEVER
        self.evicted = 0
        self.acked = self.sent = self.retries = 0
        self.waiting_since = 0.0
        """When the batches now in flight started waiting for the relay (monotonic)."""
        self._hold_s = 0.0
        """How long sending is held after the relay could not store a batch (0: it could)."""
        self.hold_until = 0.0

    @property
    def lost(self) -> int:
        """Events this node will never deliver (buffer overflow)."""
        return self.evicted + self.shed

    def put(self, events: np.ndarray) -> bool:
        """Take a copy of ``events`` (the caller may reuse its array); True if the loop should look
        at once (``batch_events`` pending, or the first pending events of an adaptive outbox)."""
        n = len(events)
        if events.dtype != EVENT_DTYPE:
            raise ValueError(f"events must be EVENT_DTYPE, not {events.dtype}")
        with self._lock:
            if self.pending_n + n > self._max_events:
                self.shed += n
                return False
            first = self.pending_n == 0
            if first:
                self._pending_since = time.monotonic()
            self._pending.append(events.copy())
            self.pending_n += n
            self.written += n
            return self.pending_n >= self.batch_events or (first and self.adaptive)

    def idle(self, connected: bool) -> bool:
        return connected and not self.inflight and not self.to_send

    def until_cut(self, connected: bool) -> float | None:
        """Adaptive batching: seconds until the pending events are due to be cut (0: now; None:
        none pending)."""
        with self._lock:
            n, since = self.pending_n, self._pending_since
        if n == 0:
            return None
        if n >= self.batch_events:
            return 0.0
        due = since + self.flush_interval_s
        if self.idle(connected):
            due = min(due, self._last_cut + self._min_flush)
        return max(0.0, due - time.monotonic())

    def cut(self) -> bool:
        """Cut what is pending into batches, queued to send; evict the oldest beyond the bound.
        False if nothing was pending."""
        with self._lock:
            pending, self._pending, self.pending_n = self._pending, [], 0
        if not pending:
            return False
        self._last_cut = time.monotonic()
        events = np.concatenate(pending) if len(pending) > 1 else pending[0]
        for i in range(0, len(events), self.batch_events):
            chunk = events[i:i + self.batch_events]
            seq = self.next_seq
            self.next_seq += 1
            data = encode_batch(self.run_id, seq, chunk, self._compress)
            self._spool(seq, len(chunk), data)
            self.unacked[seq] = (data, len(chunk))
            self._memory[seq] = len(chunk)
            self._memory_n += len(chunk)
            self.unacked_n += len(chunk)
            self.to_send.append(seq)
        while self._memory_n > self._max_events and self._memory:
            seq, n = self._memory.popitem(last=False)
            self._memory_n -= n
            if self.spool is not None and self.spool.holds(seq):
                self.unacked[seq] = (None, n)  # read back from the spool when its turn comes
            else:
                self._evict(seq)
        while len(self.doubtful) > MAX_DOUBT:  # more than a hello may ask about: given up
            self.evicted += self.doubtful.popitem(last=False)[1]
        return True

    def _spool(self, seq: int, n: int, data: bytes) -> None:
        """Batch ``seq`` onto the spool; the batches its bound dropped given up (counted lost)."""
        if self.spool is None or self.spool.broken:
            return
        try:
            dropped = self.spool.append(seq, n, data)
        except SpoolError as exc:
            log.warning("%s; this run goes on in memory only", exc)
            return
        for old, _ in dropped:
            if old in self.unacked:
                self._evict(old)

    def _evict(self, seq: int) -> None:
        """Give up unacknowledged batch ``seq``: doubtful if it was sent, else lost."""
        _, n = self.unacked.pop(seq)
        if self._memory.pop(seq, None) is not None:
            self._memory_n -= n
        self.inflight.pop(seq, None)
        self.unacked_n -= n
        if seq in self._tried:
            self._tried.discard(seq)
            self.doubtful[seq] = n
        else:
            self.evicted += n

    def load_spooled(self, batches: list[tuple[int, int]], next_seq: int) -> None:
        """A drain: the spooled batches ``(seq, events)`` are this outbox's, read from the spool
        when sent; new batches would be numbered from ``next_seq``."""
        for seq, n in batches:
            self.unacked[seq] = (None, n)
            self.unacked_n += n
            self.to_send.append(seq)
        self.written += sum(n for _, n in batches)
        self.next_seq = max(next_seq, self.next_seq)

    @property
    def spooled_n(self) -> int:
        """Unacknowledged events the spool holds (kept when the run ends)."""
        return self.spool.events if self.spool is not None else 0

    async def cut_when_due(self, wake: asyncio.Event, progress: asyncio.Event, connected: Callable[[], bool]) -> None:
        """Cut batches when they are due (the module's "Batching") until cancelled; ``progress``
        is set when some were. ``wake``: set by the exporter on a write that may be due at once (see
        :meth:`put`), a new connection, or an acknowledgement that leaves the link idle."""
        if not self.adaptive:
            while True:
                await wait_event(wake, self.flush_interval_s)
                wake.clear()
                if self.cut():
                    progress.set()
        while True:  # else sleeps until the next cut is due
            wake.clear()
            left = self.until_cut(connected())
            if left == 0.0:
                if self.cut():
                    progress.set()
                await asyncio.sleep(0)  # the sender takes the batches before a writer fills the next
            else:
                await wait_event(wake, left)

    def resend(self) -> None:
        """A new connection: everything unacknowledged goes again, in order."""
        self.inflight.clear()
        self.to_send = deque(self.unacked.keys())

    def may_send(self) -> bool:
        return bool(self.to_send) and len(self.inflight) < self._window

    def take(self) -> tuple[bytes, int] | None:
        """The next batch to send (its bytes and events), now in flight; None if it went meanwhile."""
        seq = self.to_send.popleft()
        item = self.unacked.get(seq)
        if item is None or seq in self.inflight:
            return None
        if item[0] is None:
            try:
                item = (self.spool.read(seq), item[1])
            except (SpoolError, OSError, KeyError) as exc:
                log.warning("spool: batch %d could not be read back (%s): its %d events are lost", seq, exc, item[1])
                self._evict(seq)
                return None
        if not self.inflight:
            self.waiting_since = time.monotonic()
        self.inflight[seq] = time.monotonic()
        self._tried.add(seq)
        return item

    def ack(self, ack: dict) -> str | None:
        """Take a relay's acknowledgement: "stored", "failed" (sent again once the hold ends),
        or None (not a batch in flight: ignored, or a doubtful batch now known)."""
        seq = ack.get("seq")
        if isinstance(seq, int) and seq in self.doubtful:  # evicted while in flight: now known
            self.settle_doubt(seq, ack.get("ok") is True)
            return None
        if not isinstance(seq, int) or seq not in self.inflight:
            return None
        del self.inflight[seq]
        self.waiting_since = time.monotonic()
        if ack.get("ok") is not True:
            self._hold(ack)
            self.retries += 1
            self.to_send.append(seq)
            return "failed"
        self._hold_s = 0.0
        item = self.unacked.pop(seq, None)
        self._tried.discard(seq)
        if item is not None:
            self.unacked_n -= item[1]
            self.acked += item[1]
            if self._memory.pop(seq, None) is not None:
                self._memory_n -= item[1]
            if self.spool is not None:
                self.spool.acked(seq)
        return "stored"

    def _hold(self, ack: dict) -> None:
        """Hold all sending after a batch was not stored: for what the relay asks, doubling with
        every failed round (the window's batches fail together: one round), capped."""
        now = time.monotonic()
        if now < self.hold_until:
            return
        grown = max(self._backoff[0], seconds(asked_retry_ms(ack)) or 0.0, 2 * self._hold_s)
        self._hold_s = min(grown, self._backoff[1])
        self.hold_until = now + self._hold_s

    def settle_doubt(self, seq: int, stored: bool) -> None:
        n = self.doubtful.pop(seq)
        if stored:
            self.acked += n
        else:
            self.evicted += n

    def settle_doubts(self, asked: list[int], reply: dict) -> None:
        """The relay's reply says which of the doubtful batches ``asked`` it stored; the rest
        never arrived (a relay that does not answer ``stored`` stored none it knows of)."""
        stored = reply.get("stored")
        stored = {s for s in stored if isinstance(s, int)} if isinstance(stored, list) else set()
        for seq in asked:
            if seq in self.doubtful:
                self.settle_doubt(seq, seq in stored)

    def floor(self) -> int:
        """Every batch below this was acknowledged or evicted (and not doubtful): the relay need
        not wait for it."""
        return min(next(iter(self.unacked), self.next_seq), next(iter(self.doubtful), self.next_seq))

    def report(self) -> dict:
        """What hello and clock reports tell of delivery: lost, floor, and the doubtful batches."""
        report = {"lost": self.lost, "floor": self.floor()}
        if self.doubtful:
            report["doubt"] = list(self.doubtful)
        if self.spool is not None:
            report["spool"] = self.spool.spool.facts()
        return report
