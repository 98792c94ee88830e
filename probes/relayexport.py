"""Node side of the transport: :class:`RelayExporter` ships probe events to a relay.

It implements the ``probes.events.Exporter`` protocol. ``write`` only copies the events into a
pending list under a short lock and returns: it never waits for the network. A thread of its
own runs an asyncio loop with an aiohttp WebSocket to the relay's ``/ingest`` (:mod:`probes.relaylink`)
that cuts the pending events into numbered batches (:mod:`probes.wire`; when: "Batching" below),
keeps every batch until the relay acknowledges it (the relay acknowledges after its database
committed the batch), holds all sending for a while when the relay could not store a batch (the
time the relay asks, ``retry_ms``, growing while failures go on, capped) then sends it again,
resends what is not acknowledged after a reconnect, and reconnects with exponential backoff.
The buffer of unacknowledged events is bounded (``max_buffer_events``); beyond it the oldest
batches are dropped and counted as ``lost``, a count the relay receives with the next
``hello``/``clock`` message and with ``end`` (with the lowest batch it still holds, so that the
relay stops waiting for the dropped ones). A dropped batch that was sent may have been stored
(its acknowledgement lost with the connection, or still to come): it is *doubtful* until its
acknowledgement arrives or the next hello asks the relay (``doubt``; the reply says which it
stored), or the next ``clock`` report does (every ``sync_interval_s``, and once more before
``end``); then it counts delivered or lost. The floor stays at the first doubtful batch meanwhile.
A relay that refuses the token (HTTP 401) is not asked again: :attr:`RelayExporter.refused` says
so (``dcuscope run`` ends with it as its error).

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

Several relays (``--relay URL1,URL2``, relays that share one database): the node ships to one at
a time and moves to the next in the list, round robin, when the one it uses cannot be reached
(its TCP connect fails or takes over ``CONNECT_TIMEOUT_S``, its WebSocket handshake over
``HANDSHAKE_TIMEOUT_S``), when its connection drops, when it is silent (the node waits for it,
batches in flight or a request, and hears nothing for ``SILENCE_S``, not even the answer to a
ping: a frozen relay keeps its connections open), or when it answers hello with "later" (``ok:
false`` with ``retry_ms``, e.g. its store fails). A relay that answers that another relay holds
the run is asked again after the wait it gives, for up to ``ELSEWHERE_PATIENCE_S`` (the holder's
lease runs out, or it lets the run go, within seconds), then the next. The next relay is tried at
once; the backoff (or the wait a relay asked for) runs between rounds, once every relay of the
list failed or asked to come back later. The node never gives up while its run is open. The run
goes on there, resumed with its secret, its unacknowledged batches resent. A relay that refuses
the node for now (another live run holds its name) is asked again after the backoff, as with one
relay; a refused token ends the tries.
Each move is logged once per outage ("relay URL1 unreachable; trying URL2").

On each connection it also measures the clock offset to the relay and reports the samples with
the node's linuxptp state (``clock``); the relay estimates. The exchanges go over UDP beside the
WebSocket when the relay offers it (:mod:`probes.udpclock`: kernel timestamps, bursts of 16),
else, or when UDP gets no answer, over the WebSocket (``sync``): said once.
"""

from __future__ import annotations

import asyncio
import logging
import random
import threading
import time
import uuid
from collections import OrderedDict, deque
from typing import NamedTuple, Sequence

import aiohttp
import numpy as np
from yarl import URL

from core.clocks import CLOCKS, NEVER, PretendClock
from probes.errors import ExportError
from probes.events import EVENT_DTYPE, EXPORTER_CLOSE_S, TraceHeader
from probes.ptp import POLL_INTERVAL_S, PtpWatch
from probes.relaylink import ELSEWHERE, Link, Refused, asked_retry_ms, parse_relays
from probes.udpclock import UdpClock, parse_offer
from probes.sysclock import DEFAULT_UDS
from probes.wire import HEARTBEAT_S, MAX_BATCH_EVENTS, MAX_DOUBT, PROTOCOL_VERSION, SILENCE_S, encode_batch

DEFAULT_BATCH_EVENTS = 8192
DEFAULT_FLUSH_INTERVAL_S = 0.05
"""The longest an event is held on the node before it is cut into a batch (``adaptive=False``:
the period of the cuts)."""
DEFAULT_MIN_FLUSH_S = 0.04
"""Adaptive batching: the shortest time between two cuts that an idle link triggers. A relay's
work per batch (decode, commit, acknowledgement, a pairing merge) is most of its cost at a DCU's
pace: 40 ms instead of 10 holds a paced DCU to 25 batches a second, which took the relay's CPU
per event from 19.7 to 13.4 µs (8 DCUs, BENCHMARKS.md, issue 31) for about 20 ms more lag."""
DEFAULT_MAX_BUFFER_EVENTS = 2_000_000
"""About 46 MiB, 7.7 minutes of a paper-sized DCU (4,300 events/s)."""
DEFAULT_WINDOW = 64
"""Batches in flight (sent, not acknowledged) on one connection."""
SYNC_BURST_FIRST, SYNC_BURST = 8, 4
ACK_TIMEOUT_S = 30.0
SILENCE_CHECK_S = 0.25
"""How often the sender, waiting, looks whether the relay went silent."""
CONNECT_TIMEOUT_S = 2.0
"""A relay whose TCP connect takes longer counts as unreachable: a relay host that is down (its
SYNs unanswered) is left for the next relay within this, not after the whole handshake's bound."""
HELLO_TIMEOUT_S = 10.0
SYNC_TIMEOUT_S = 10.0
UDP_RETRY_S = 30.0
"""After a UDP burst got no answer, the WebSocket exchanges serve this long before UDP is tried again."""
ELSEWHERE_PATIENCE_S = 8.0
"""How long a relay that says another relay holds the run is asked again before the next is tried:
longer than a lease (``relay.store.base.LEASE_S``) plus the time a relay takes to see its node gone
(``probes.wire.SILENCE_S``)."""
CLOSE_SAY_S = 5.0
"""While ``close`` waits for a relay, what it waits for is said this often."""
END_TIMEOUT_S = 2.0
"""Of ``close_timeout_s``, kept to say ``end``."""
TEARDOWN_S = 1.5
"""Of ``close_timeout_s``, kept to close the WebSocket and end the thread."""

log = logging.getLogger(__name__)


class RelayExporter:
    """Ships events to ``url`` (``http://HOST:PORT``) as node ``node``; ``url`` may name several
    relays (``"URL1,URL2"`` or a list, see :func:`probes.relaylink.parse_relays`), tried in turn.

    ``clock`` names the clock the probes read (``probes.events.CLOCKS``): the NTP exchanges
    must read the same one. ``pretend`` is a testing aid: every clock reading of this client
    goes through it, as the probes' event timestamps do, to inject a known offset and drift.
    ``close_timeout_s`` bounds ``close`` as a whole (waiting for acknowledgements included).
    ``ptp_socket``: the UDS of the local ptp4l, read every ``ptp_interval_s`` with pmc.
    ``adaptive``, ``min_flush_s``, ``flush_interval_s``, ``batch_events``: how pending events are
    cut into batches (the module's "Batching").
    """

    def __init__(self, url: str | Sequence[str], node: str, token: str | None = None, clock: str = "realtime",
                 pretend: PretendClock | None = None, *, compress: bool = False,
                 batch_events: int = DEFAULT_BATCH_EVENTS, flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
                 adaptive: bool = True, min_flush_s: float = DEFAULT_MIN_FLUSH_S,
                 max_buffer_events: int = DEFAULT_MAX_BUFFER_EVENTS, window: int = DEFAULT_WINDOW,
                 sync_interval_s: float = 2.0, ptp_interval_s: float = POLL_INTERVAL_S,
                 ptp_socket: str = DEFAULT_UDS,
                 close_timeout_s: float = EXPORTER_CLOSE_S,
                 backoff_s: tuple[float, float] = (0.1, 5.0)) -> None:
        if clock not in CLOCKS:
            raise ExportError(f"relay exporter: unknown clock {clock!r} (one of {', '.join(CLOCKS)})")
        self.urls = parse_relays(url)
        if not node:
            raise ExportError("relay exporter: the node needs a name")
        self.node, self._token = node, token
        self.url = self.urls[0]
        """The relay of ``urls`` in use: connected, or the one tried next."""
        self._pretend = pretend if pretend is not None else PretendClock(clock_id=CLOCKS[clock])
        if self._pretend.clock_id != CLOCKS[clock]:
            raise ExportError(f"relay exporter: the pretend clock reads clock {self._pretend.clock_id}, not {clock}")
        self._compress = compress
        self._batch_events = max(1, min(int(batch_events), MAX_BATCH_EVENTS))
        self._flush_interval = flush_interval_s
        self._adaptive, self._min_flush = adaptive, min_flush_s
        self._max_events = int(max_buffer_events)
        self._window = max(1, int(window))
        self._sync_interval, self._ptp_interval = sync_interval_s, ptp_interval_s
        self.close_timeout_s, self._backoff = close_timeout_s, backoff_s
        """How long ``close`` keeps trying every relay for the acknowledgements and ``end``."""
        self.run_id = uuid.uuid4().hex
        self._secret: str | None = None
        """The relay's resume secret for this run (its first hello's reply): only with it may a
        connection resume the run."""
        self._header: dict | None = None

        # Shared with the caller's thread: only these, under the lock.
        self._lock = threading.Lock()
        self._pending: list[np.ndarray] = []
        self._pending_n = 0
        self._pending_since = 0.0  # monotonic time of the oldest pending write
        self._shed = 0  # events refused by write because even the pending list was full

        # Owned by the loop thread.
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._unacked: OrderedDict[int, tuple[bytes, int]] = OrderedDict()
        self._unacked_n = 0
        self._inflight: dict[int, float] = {}
        self._tried: set[int] = set()
        """Unacknowledged batches sent at least once (on any connection)."""
        self._doubtful: OrderedDict[int, int] = OrderedDict()
        """Evicted batches that were sent: seq -> events (module doc)."""
        self._to_send: deque[int] = deque()
        self._next_seq = 0
        self._last_cut = NEVER
        self._evicted = 0
        self._written = self._acked = self._sent = self._connects = 0
        self._connected = False
        self._last_error = ""
        self._moves_said: set[tuple[str, str, str]] = set()
        """Moves to another relay logged since the last hello: each said once per outage."""
        self._retries = 0
        self._elsewhere_since: float | None = None
        """When the relay in use first answered that another relay holds the run (None: it did not)."""
        self._waiting_since = 0.0
        """When the batches now in flight started waiting for the relay (monotonic)."""
        self._hold_s = 0.0
        """How long sending is held after the relay could not store a batch (0: it could)."""
        self._hold_until = 0.0
        self._ptp: dict = {"state": "unavailable", "reason": "not read yet"}
        self._ptp_watch = PtpWatch(ptp_socket)
        self._link: Link | None = None
        self._offer: tuple[int, bytes] | None = None
        """(port, key) of the UDP clock exchange the relay offered on this connection."""
        self._udp_failed_at: float | None = None
        self._udp_said = False
        self.clock_via = ""
        """How the last clock samples travelled: udp or websocket."""
        self.refused: str | None = None
        """Why the relay refused this node (a wrong or missing token), if it did."""

    # --- Exporter protocol (the probe shipping thread) -----------------------------------

    def start(self, header: TraceHeader) -> None:
        if self._thread is not None:
            raise ExportError("relay exporter already started")
        d = header.to_dict()
        if d["node"] != self.node:
            log.warning("trace header names node %r, shipping it as %r", d["node"], self.node)
            d["node"] = self.node
        self._header = d
        ready = threading.Event()
        self._thread = threading.Thread(target=self._thread_main, args=(ready,), daemon=True,
                                         name=f"dcuscope-relay-{self.node}")
        self._thread.start()
        ready.wait(10)

    def write(self, events: np.ndarray) -> None:
        n = len(events)
        if n == 0:
            return
        if events.dtype != EVENT_DTYPE:
            raise ValueError(f"events must be EVENT_DTYPE, not {events.dtype}")
        with self._lock:
            if self._pending_n + n > self._max_events:
                self._shed += n
                return
            first = self._pending_n == 0
            if first:
                self._pending_since = time.monotonic()
            # A copy: the shipper may reuse its array after write returns.
            self._pending.append(events.copy())
            self._pending_n += n
            self._written += n
            # Adaptive: the first pending events may go at once (an idle link), or set the hold's end.
            wake = self._pending_n >= self._batch_events or (first and self._adaptive)
        if wake and self._loop is not None:
            self._loop.call_soon_threadsafe(self._wake.set)

    def close(self, dropped: int) -> None:
        """Send what is buffered, tell the relay the run ended; all within ``close_timeout_s``."""
        if self._thread is None or self._loop is None:
            return
        deadline = time.monotonic() + self.close_timeout_s
        future = asyncio.run_coroutine_threadsafe(self._finish(int(dropped), deadline), self._loop)
        try:
            future.result(max(0.0, deadline - time.monotonic()))
        except Exception as exc:  # noqa: BLE001 - closing must not raise into the pipeline's teardown
            log.warning("relay exporter %s: close: %s", self.node, exc or type(exc).__name__)
        self._thread.join(max(0.0, deadline - time.monotonic()))

    # --- introspection ------------------------------------------------------------------------

    @property
    def lost(self) -> int:
        """Events this node will never deliver (buffer overflow)."""
        return self._evicted + self._shed

    def counters(self) -> dict:
        return {
            "run": self.run_id, "connected": self._connected, "relay": self.url if self._connected else "",
            "connects": self._connects, "batches": self._next_seq,
            "written": self._written, "sent": self._sent, "acked": self._acked, "lost": self.lost,
            "buffered": self._unacked_n + self._pending_n, "retries": self._retries,
            "last_error": self._last_error, "clock_via": self.clock_via,
        }

    # --- loop thread --------------------------------------------------------------------------

    def _thread_main(self, ready: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._wake = asyncio.Event()
        self._progress = asyncio.Event()
        self._stop = asyncio.Event()
        self._synced = asyncio.Event()  # the relay got a clock report on this connection
        self._loop = loop  # last: write() uses it as the sign that _wake exists
        ready.set()
        try:
            loop.run_until_complete(self._main())
        except Exception:  # noqa: BLE001 - a dying shipper must say why, not kill the process
            log.exception("relay exporter %s stopped", self.node)
        finally:
            loop.close()

    def _now(self) -> int:
        return self._pretend.now()

    async def _main(self) -> None:
        tasks = [asyncio.create_task(self._flush_loop()), asyncio.create_task(self._ptp_loop())]
        try:
            await self._connection_loop()
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _flush_loop(self) -> None:
        if not self._adaptive:
            while True:
                await _wait(self._wake, self._flush_interval)
                self._wake.clear()
                self._cut_batches()
        # Woken by write (the first pending events, or batch_events of them), by a new connection
        # and by the acknowledgement that leaves the link idle; else sleeps until the next cut is due.
        while True:
            self._wake.clear()
            left = self._until_cut()
            if left == 0.0:
                self._cut_batches()
                await asyncio.sleep(0)  # the sender takes the batches before a writer fills the next
            else:
                await _wait(self._wake, left)

    def _until_cut(self) -> float | None:
        """Adaptive batching: seconds until the pending events are due to be cut (0: now; None:
        none pending)."""
        with self._lock:
            n, since = self._pending_n, self._pending_since
        if n == 0:
            return None
        if n >= self._batch_events:
            return 0.0
        due = since + self._flush_interval
        if self._link_idle():
            due = min(due, self._last_cut + self._min_flush)
        return max(0.0, due - time.monotonic())

    def _link_idle(self) -> bool:
        return self._connected and not self._inflight and not self._to_send

    def _cut_batches(self) -> None:
        with self._lock:
            pending, self._pending, self._pending_n = self._pending, [], 0
        if not pending:
            return
        self._last_cut = time.monotonic()
        events = np.concatenate(pending) if len(pending) > 1 else pending[0]
        for i in range(0, len(events), self._batch_events):
            chunk = events[i:i + self._batch_events]
            seq = self._next_seq
            self._next_seq += 1
            self._unacked[seq] = (encode_batch(self.run_id, seq, chunk, self._compress), len(chunk))
            self._unacked_n += len(chunk)
            self._to_send.append(seq)
        while self._unacked_n > self._max_events and self._unacked:
            seq, (_, n) = self._unacked.popitem(last=False)
            self._inflight.pop(seq, None)
            self._unacked_n -= n
            if seq in self._tried:
                self._tried.discard(seq)
                self._doubtful[seq] = n
            else:
                self._evicted += n
        while len(self._doubtful) > MAX_DOUBT:  # more than a hello may ask about: given up
            self._evicted += self._doubtful.popitem(last=False)[1]
        self._progress.set()

    def _settle_doubt(self, seq: int, stored: bool) -> None:
        n = self._doubtful.pop(seq)
        if stored:
            self._acked += n
        else:
            self._evicted += n

    def _settle_doubts(self, asked: list[int], reply: dict) -> None:
        """The relay's reply says which of the doubtful batches ``asked`` it stored; the rest
        never arrived (a relay that does not answer ``stored`` stored none it knows of)."""
        stored = reply.get("stored")
        stored = {s for s in stored if isinstance(s, int)} if isinstance(stored, list) else set()
        for seq in asked:
            if seq in self._doubtful:
                self._settle_doubt(seq, seq in stored)

    async def _ptp_loop(self) -> None:
        while True:
            self._ptp = await self._ptp_watch.read()
            await asyncio.sleep(self._ptp_interval)

    def _hello(self) -> dict:
        hello = {"proto": PROTOCOL_VERSION, "run": self.run_id, "header": self._header,
                 "lost": self.lost, "floor": self._floor(), "ptp": self._ptp}
        if self._doubtful:
            hello["doubt"] = list(self._doubtful)
        if self._secret is not None:
            hello["secret"] = self._secret
        return hello

    def _floor(self) -> int:
        """Every batch below this was acknowledged or evicted (and not doubtful): the relay need
        not wait for it."""
        return min(next(iter(self._unacked), self._next_seq), next(iter(self._doubtful), self._next_seq))

    async def _connection_loop(self) -> None:
        delay = self._backoff[0]
        misses = 0  # relays in a row that could not be reached
        laters = 0  # relays in a row that asked to come back later
        # total=None: the handshake has its own bound (relaylink), and the WebSocket lives on.
        timeout = aiohttp.ClientTimeout(total=None, sock_connect=CONNECT_TIMEOUT_S)
        async with aiohttp.ClientSession(timeout=timeout) as session:
            while not self._stop.is_set():
                outcome = await self._connect_unless_stopped(session)
                if self.refused:
                    break  # no use asking again: close() reports it
                if outcome is None:
                    continue  # stopped
                if isinstance(outcome, Link):
                    delay, misses, laters = self._backoff[0], 0, 0
                    self._elsewhere_since = None
                    self._moves_said.clear()
                    why = await self._serve(outcome)
                    if not self._stop.is_set():
                        self._move_on(f"connection to relay {self.url} lost", why)
                    continue
                if outcome.kind == _ELSEWHERE and self._patient():
                    misses = 0
                    # The run's holder lets it go (its node left it) or its lease runs out: this relay takes it then.
                    wait = min(outcome.wait_s, self._backoff[1]) if outcome.wait_s is not None else delay
                    self._note_error(f"relay {self.url}: another relay holds this run; asking again")
                elif outcome.kind in (_LATER, _ELSEWHERE):
                    misses, laters = 0, laters + 1
                    self._elsewhere_since = None
                    # The next relay at once (its store may work); once every relay asked, as long as
                    # the last asks, within the backoff's cap.
                    asked = min(outcome.wait_s, self._backoff[1]) if outcome.wait_s is not None else delay
                    wait = asked if laters % len(self.urls) == 0 else 0.0
                    self._move_on(f"relay {self.url} asks to come back later", outcome.why, wait)
                elif outcome.kind == _REFUSED:
                    misses, wait = 0, delay
                    self._note_error(f"relay {self.url} refused this node for now: {outcome.why}")
                else:
                    misses += 1
                    self._move_on(f"relay {self.url} unreachable", outcome.why,
                                  alone=f"cannot reach relay {self.url}")
                    # The next relay at once; the backoff once every relay of the list failed.
                    wait = delay if misses % len(self.urls) == 0 else 0.0
                if wait:
                    if outcome.wait_s is None:
                        delay = min(delay * 2, self._backoff[1])
                        wait *= random.uniform(0.8, 1.2)
                    await _wait(self._stop, wait)
        await self._stop.wait()

    def _patient(self) -> bool:
        """Whether the relay that says another holds the run is to be asked again (not the next)."""
        now = time.monotonic()
        if self._elsewhere_since is None:
            self._elsewhere_since = now
        return now - self._elsewhere_since < ELSEWHERE_PATIENCE_S

    def _move_on(self, what: str, why: str, wait_s: float = 0.0, alone: str | None = None) -> None:
        """Take the next relay of the list and say why; with one relay, say why (or ``alone``)."""
        if len(self.urls) == 1:
            what = alone or what
            self._note_error(f"{what}: {why}" if why else what)
            return
        previous = self.url
        self.url = self.urls[(self.urls.index(previous) + 1) % len(self.urls)]
        then = f" in {wait_s:.1f} s" if wait_s else ""
        self._last_error = f"{what}; trying {self.url}{then}" + (f" ({why})" if why else "")
        # Said once per outage: while no relay answers, the node goes round the list quietly.
        if (previous, self.url, what) not in self._moves_said:
            self._moves_said.add((previous, self.url, what))
            log.warning("relay exporter %s: %s", self.node, self._last_error)

    async def _connect_unless_stopped(self, session: aiohttp.ClientSession) -> Link | _Miss | None:
        """The link, why there is none, or None if the exporter stopped meanwhile."""
        # close() must not wait out a handshake with a relay that does not answer.
        connecting = asyncio.create_task(self._connect(session))
        stopping = asyncio.create_task(self._stop.wait())
        await asyncio.wait([connecting, stopping], return_when=asyncio.FIRST_COMPLETED)
        stopping.cancel()
        if connecting.done():
            return connecting.result()
        connecting.cancel()
        await asyncio.gather(connecting, return_exceptions=True)
        return None

    async def _connect(self, session: aiohttp.ClientSession) -> Link | _Miss:
        """A link that said hello, or why not."""
        try:
            link = await Link.open(session, self.url, self._token, self._on_ack)
        except Refused as exc:
            # Not logged: the run ends with this as its one error line (probes.instrument).
            self.refused = self._last_error = str(exc)
            return _Miss(_REFUSED, str(exc))
        except ExportError as exc:
            return _Miss(_UNREACHABLE, str(exc))
        hello = self._hello()
        try:
            reply = await link.call("hello", hello, HELLO_TIMEOUT_S)
        except (ConnectionError, TimeoutError, aiohttp.ClientError) as exc:
            await link.close()
            if link.elsewhere:  # another relay holds the run: not a refusal of this node
                return _Miss(_ELSEWHERE, link.error, _seconds(link.retry_ms))
            if link.error.startswith("relay error"):
                # The relay said why (e.g. another live run holds this node's name): it is asked again later.
                return _Miss(_REFUSED, link.error)
            return _Miss(_UNREACHABLE, link.error or _describe(exc))
        if not (isinstance(reply, dict) and reply.get("ok")):
            # A relay that cannot take the run now (it says for how long, with retry_ms).
            await link.close()
            kind = _ELSEWHERE if ELSEWHERE.search(str(reply.get("error") if isinstance(reply, dict) else "")) else _LATER
            return _Miss(kind, f"relay refused hello: {str(reply)[:200]}", _seconds(asked_retry_ms(reply)))
        if isinstance(reply.get("secret"), str):
            self._secret = reply["secret"]
        self._settle_doubts(hello.get("doubt", []), reply)
        self._offer = parse_offer(reply)
        return link

    async def _serve(self, link: Link) -> str:
        """Ship on ``link`` until it ends or the exporter stops; why it ended ("" if it said nothing)."""
        self._connects += 1
        self._connected, self._link = True, link
        self._inflight.clear()
        self._synced.clear()
        self._to_send = deque(self._unacked.keys())
        self._wake.set()  # adaptive batching: an idle link may take what is pending
        workers = [asyncio.create_task(self._sender(link)), asyncio.create_task(self._syncer(link))]
        stop = asyncio.create_task(self._stop.wait())
        lost = asyncio.create_task(link.closed())
        await asyncio.wait([stop, lost, *workers], return_when=asyncio.FIRST_COMPLETED)
        for t in (stop, lost, *workers):
            t.cancel()
        # Let them finish here, on the loop: a task left pending is closed when the loop is gone,
        # its cleanup (the UDP clock socket) then failing outside any loop, printed at exit.
        await asyncio.gather(stop, lost, *workers, return_exceptions=True)
        failed = [t.exception() for t in workers if t.done() and not t.cancelled() and t.exception() is not None]
        self._connected, self._link = False, None
        await link.close()
        return link.error or (_describe(failed[0]) if failed else "")

    async def _sender(self, link: Link) -> None:
        while True:
            self._check_silence(link)
            while self._to_send and len(self._inflight) < self._window:
                if time.monotonic() < self._hold_until:  # the relay's storage fails: hold every batch
                    await asyncio.sleep(self._hold_until - time.monotonic())
                    continue
                seq = self._to_send.popleft()
                item = self._unacked.get(seq)
                if item is None or seq in self._inflight:
                    continue
                if not self._inflight:
                    self._waiting_since = time.monotonic()
                self._inflight[seq] = time.monotonic()
                self._tried.add(seq)
                await link.send_batch(item[0])
                self._sent += item[1]
            self._progress.clear()
            if not await _wait(self._progress, SILENCE_CHECK_S):
                since = self._expecting(link)
                if since is not None and link.silent_s(since) >= HEARTBEAT_S:
                    await link.ping()
                oldest = min(self._inflight.values(), default=time.monotonic())
                if time.monotonic() - oldest > ACK_TIMEOUT_S:
                    raise ExportError(f"no acknowledgement for {ACK_TIMEOUT_S:.0f} s") from None

    def _expecting(self, link: Link) -> float | None:
        """Since when the node has been waiting for the relay (batches in flight, a request's
        reply), or None if it waits for nothing."""
        starts = ([self._waiting_since] if self._inflight else []) + ([link.asked_at] if link.asked_at else [])
        return min(starts, default=None)

    def _check_silence(self, link: Link) -> None:
        """A relay that, while the node waits for it, said nothing for SILENCE_S (not even a pong)
        is left: it froze, or the network between is cut."""
        since = self._expecting(link)
        if since is not None:
            silent = link.silent_s(since)
            if silent >= SILENCE_S:
                raise ExportError(f"relay silent for {silent:.1f} s with {len(self._inflight)} batches "
                                  "unacknowledged")

    def _on_ack(self, ack: dict) -> None:
        seq = ack.get("seq")
        if isinstance(seq, int) and seq in self._doubtful:  # evicted while in flight: now known
            self._settle_doubt(seq, ack.get("ok") is True)
            return
        if not isinstance(seq, int) or seq not in self._inflight:
            return
        del self._inflight[seq]
        self._waiting_since = time.monotonic()
        if ack.get("ok") is not True:
            self._hold(ack)
            self._retries += 1
            # One line while it lasts (no seq in it): every batch fails alike.
            self._note_error(f"relay could not store batches: {str(ack.get('error'))[:100]}; holding them")
            self._to_send.append(seq)  # sent again, on this connection, once the hold ends
            self._progress.set()
            return
        self._hold_s = 0.0
        item = self._unacked.pop(seq, None)
        self._tried.discard(seq)
        if item is not None:
            self._unacked_n -= item[1]
            self._acked += item[1]
        self._progress.set()
        if self._adaptive and self._link_idle():
            self._wake.set()  # what gathered meanwhile may go now

    def _hold(self, ack: dict) -> None:
        """Hold all sending after a batch was not stored: for what the relay asks, doubling with
        every failed round (the window's batches fail together: one round), capped."""
        now = time.monotonic()
        if now < self._hold_until:
            return
        grown = max(self._backoff[0], _seconds(asked_retry_ms(ack)) or 0.0, 2 * self._hold_s)
        self._hold_s = min(grown, self._backoff[1])
        self._hold_until = now + self._hold_s

    async def _syncer(self, link: Link) -> None:
        udp = await self._open_udp()
        burst = SYNC_BURST_FIRST
        try:
            while True:
                report = self._clock_report()
                samples = await self._udp_burst(udp) if udp is not None else []
                if samples:
                    report.update(samples=samples, via="udp")
                else:
                    report["samples"] = await self._ws_burst(link, burst)
                self.clock_via = report.get("via", "websocket")
                await self._report_clock(link, report)
                self._synced.set()
                burst = SYNC_BURST
                await asyncio.sleep(self._sync_interval)
        finally:
            if udp is not None:
                udp.close()

    def _clock_report(self) -> dict:
        report = {"lost": self.lost, "floor": self._floor(), "ptp": self._ptp}
        if self._doubtful:
            report["doubt"] = list(self._doubtful)
        return report

    async def _report_clock(self, link: Link, report: dict) -> None:
        """Send a clock report; one that asks about doubtful batches waits for the answer."""
        if "doubt" not in report:
            await link.tell("clock", report)
            return
        reply = await link.call("clock", report, SYNC_TIMEOUT_S)
        if isinstance(reply, dict):
            self._settle_doubts(report["doubt"], reply)

    async def _open_udp(self) -> UdpClock | None:
        if self._offer is None:
            self._say_once("the relay offers no UDP clock exchange (an older relay, or --clock-port 0)")
            return None
        host = URL(self.url).host or ""
        try:
            return await UdpClock.open(host, self._offer[0], self._offer[1], self._pretend)
        except OSError as exc:
            self._say_once(f"cannot open the UDP clock exchange to {host}:{self._offer[0]}: {_describe(exc)}")
            return None

    async def _udp_burst(self, udp: UdpClock) -> list[list[int]]:
        if self._udp_failed_at is not None and time.monotonic() - self._udp_failed_at < UDP_RETRY_S:
            return []
        samples = await udp.burst()
        if samples:
            self._udp_failed_at = None
            return samples
        self._udp_failed_at = time.monotonic()
        self._say_once(f"no answer to UDP clock exchanges on port {self._offer[0] if self._offer else '?'} "
                       f"(blocked?)")
        return []

    def _say_once(self, why: str) -> None:
        """Falling back to the WebSocket exchange is said once per run, not per connection."""
        if not self._udp_said:
            self._udp_said = True
            log.warning("relay exporter %s: %s; clock samples go over the WebSocket", self.node, why)

    async def _ws_burst(self, link: Link, burst: int) -> list[list[int]]:
        samples = []
        for _ in range(burst):
            t1 = self._now()
            reply = await link.call("sync", None, SYNC_TIMEOUT_S)
            t4 = self._now()
            if isinstance(reply, dict) and isinstance(reply.get("t2"), int) and isinstance(reply.get("t3"), int):
                samples.append([t1, reply["t2"], reply["t3"], t4])
        return samples

    def _note_error(self, message: str) -> None:
        if message != self._last_error:
            log.warning("relay exporter %s: %s", self.node, message)
        self._last_error = message

    async def _finish(self, dropped: int, deadline: float) -> None:
        """Wait for the acknowledgements, trying every relay, until ``deadline`` leaves time to say
        ``end``; then say it (to whichever relay answers)."""
        self._cut_batches()
        # What close() keeps to say end and tear down: at most half its time, so that a short
        # close_timeout_s still waits for acknowledgements (or a first answer from the relay).
        reserve = min(END_TIMEOUT_S + TEARDOWN_S, self.close_timeout_s / 2)
        acks_until = deadline - reserve
        await self._await_relay(acks_until, deadline)
        if self._link is not None:
            # A short run still leaves the relay its clock estimate.
            await _wait(self._synced, max(0.0, acks_until - time.monotonic()))
        if self._unacked and not self.refused:  # a refusal is the whole story
            log.warning("relay exporter %s: %d events not acknowledged at close", self.node, self._unacked_n)
        link = self._link
        if link is not None and self._doubtful:
            try:
                await self._report_clock(link, self._clock_report())
            except (ConnectionError, TimeoutError, aiohttp.ClientError) as exc:
                self._note_error(f"could not ask the relay about doubtful batches: {_describe(exc)}")
        for seq in list(self._doubtful):  # not known: counted lost
            self._settle_doubt(seq, False)
        await self._say_end(dropped, deadline - reserve * TEARDOWN_S / (END_TIMEOUT_S + TEARDOWN_S))
        self._stop.set()

    async def _await_relay(self, until: float, deadline: float) -> None:
        """Until every batch is acknowledged and a relay is connected (to hear ``end``), or
        ``until``: the connection loop goes on trying every relay meanwhile. What it waits for is
        said every CLOSE_SAY_S."""
        said = time.monotonic()
        while (self._unacked or self._link is None) and not self.refused and time.monotonic() < until:
            if time.monotonic() - said >= CLOSE_SAY_S:
                said = time.monotonic()
                what = (f"{self._unacked_n} events to be acknowledged" if self._unacked
                        else "a relay to hear that the run ended")
                where = f"relay {self.url}" if self._connected else f"no relay connected ({self._last_error})"
                log.warning("relay exporter %s: closing: waiting for %s; %s; %.0f s left (--close-timeout)",
                            self.node, what, where, max(0.0, deadline - time.monotonic()))
            self._progress.clear()
            await _wait(self._progress, min(0.2, max(until - time.monotonic(), 0.01)))

    async def _say_end(self, dropped: int, until: float) -> None:
        """Tell the relay the run ended; a relay lost meanwhile is replaced by the next that answers."""
        while not self.refused and time.monotonic() < until:
            link = self._link
            if link is None:
                await asyncio.sleep(0.1)
                continue
            end = {"events": self._written, "dropped": dropped, "lost": self.lost + self._unacked_n}
            try:
                await link.call("end", end, max(0.1, min(END_TIMEOUT_S, until - time.monotonic())))
                return
            except (ConnectionError, TimeoutError, aiohttp.ClientError) as exc:
                self._note_error(f"could not send end: {_describe(exc)}")
                await asyncio.sleep(0.1)


_UNREACHABLE, _REFUSED, _LATER, _ELSEWHERE = "unreachable", "refused", "later", "elsewhere"


class _Miss(NamedTuple):
    """Why a connection attempt gave no link: the relay could not be reached, refused this node
    (for now, or its token: :attr:`RelayExporter.refused`), asked it to come back later (after
    ``wait_s``, if it said), or said that another relay holds its run."""

    kind: str
    why: str
    wait_s: float | None = None


def _seconds(ms: int | None) -> float | None:
    return ms / 1000 if ms is not None else None


async def _wait(event: asyncio.Event, timeout_s: float | None) -> bool:
    """Wait for ``event`` at most ``timeout_s`` (None: for as long as it takes); True if it was
    set. (``asyncio.timeout`` costs no extra task per wait, unlike ``wait_for``: this runs up to
    hundreds of times a second.)"""
    try:
        async with asyncio.timeout(timeout_s):
            await event.wait()
        return True
    except TimeoutError:
        return False


def _describe(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__
