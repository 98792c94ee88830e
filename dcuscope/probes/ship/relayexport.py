"""Node side of the transport: :class:`RelayExporter` ships probe events to a relay.

It implements the ``protocol.events.Exporter`` protocol. ``write`` only copies the events into
the outbox under a short lock and returns: it never waits for the network. A thread of its own
runs an asyncio loop with an aiohttp WebSocket to the relay's ``/ingest`` (:mod:`dcuscope.probes.ship.relaylink`)
and composes the parts of the node's side:

- :mod:`dcuscope.probes.ship.outbox`: pending events cut into numbered batches (adaptive batching), kept
  until acknowledged, bounded, doubtful batches settled; sending held while the relay cannot
  store;
- :mod:`dcuscope.probes.ship.failover`: which relay of ``--relay URL1,URL2`` is used, when the node moves
  on, backoff between rounds; a refused token ends the tries (:attr:`RelayExporter.refused`);
- :mod:`dcuscope.probes.ship.sending`: batches sent within the window on one link; a silent relay left;
- :mod:`dcuscope.probes.ship.clockreport`: clock samples (UDP or WebSocket) and PTP state, reported on
  every connection.

Here: the thread, the run's resumption on every connection (its secret, its unacknowledged
batches resent), and closing, which waits for the acknowledgements (trying every relay) and says
``end``, all within ``close_timeout_s``.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
import uuid
from typing import Callable, Sequence

import aiohttp
import numpy as np

from dcuscope.core.clocks import CLOCKS, PretendClock
from dcuscope.core.pycompat import ASYNC_TIMEOUTS
from dcuscope.probes.clocks.ptp import POLL_INTERVAL_S
from dcuscope.probes.clocks.sysclock import DEFAULT_UDS
from dcuscope.probes.ship.aio import describe, wait_event
from dcuscope.probes.ship.clockreport import ClockReporter
from dcuscope.probes.ship.delivery import Delivery
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.failover import Failover
from dcuscope.probes.ship.nodetls import RelayTls
from dcuscope.protocol.clockdatagram import parse_offer
from dcuscope.probes.ship.outbox import (DEFAULT_BATCH_EVENTS, DEFAULT_FLUSH_INTERVAL_S, DEFAULT_MAX_BUFFER_EVENTS,
                                DEFAULT_MIN_FLUSH_S, DEFAULT_WINDOW, Outbox)
from dcuscope.probes.ship.relaylink import Link
from dcuscope.probes.ship.runspool import RunSpool
from dcuscope.probes.ship.sending import send
from dcuscope.probes.ship.spool import Spool
from dcuscope.probes.ship.spoolfile import SpoolError
from dcuscope.protocol.events import EXPORTER_CLOSE_S, TraceHeader
from dcuscope.protocol.wire import PROTOCOL_VERSION

CLOSE_SAY_S = 5.0
"""While ``close`` waits for a relay, what it waits for is said this often."""
END_TIMEOUT_S = 2.0
"""Of ``close_timeout_s``, kept to say ``end``."""
TEARDOWN_S = 1.5
"""Of ``close_timeout_s``, kept to close the WebSocket and end the thread."""
CUT_WAIT_S = 60.0
"""The longest ``close`` waits for what was written to be cut into batches (spooled, or counted lost at
the bounds) before ``close_timeout_s`` starts: local work, encoding and the spool's disk, not the relay's."""

log = logging.getLogger(__name__)


class RelayExporter:
    """Ships events to ``url`` (``http://HOST:PORT``) as node ``node``; ``url`` may name several
    relays (``"URL1,URL2"`` or a list, see :func:`dcuscope.probes.ship.relaylink.parse_relays`), tried in turn.

    ``clock`` names the clock the probes read (``protocol.events.CLOCKS``): the NTP exchanges
    must read the same one. ``pretend`` is a testing aid: every clock reading of this client
    goes through it, as the probes' event timestamps do, to inject a known offset and drift.
    ``close_timeout_s`` bounds ``close`` as a whole (waiting for acknowledgements included).
    ``ptp_socket``: the UDS of the local ptp4l, read every ``ptp_interval_s`` with pmc.
    ``adaptive``, ``min_flush_s``, ``flush_interval_s``, ``batch_events``: how pending events are
    cut into batches (:mod:`dcuscope.probes.ship.outbox`). ``tls``: how ``https://`` relays are verified and
    this node's certificate (:mod:`dcuscope.probes.ship.nodetls`; None: the system's CAs, no certificate).
    """

    def __init__(self, url: str | Sequence[str], node: str, token: str | None = None, clock: str = "realtime",
                 pretend: PretendClock | None = None, *, compress: bool = False,
                 batch_events: int = DEFAULT_BATCH_EVENTS, flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
                 adaptive: bool = True, min_flush_s: float = DEFAULT_MIN_FLUSH_S,
                 max_buffer_events: int = DEFAULT_MAX_BUFFER_EVENTS, window: int = DEFAULT_WINDOW,
                 sync_interval_s: float = 2.0, ptp_interval_s: float = POLL_INTERVAL_S,
                 ptp_socket: str = DEFAULT_UDS,
                 close_timeout_s: float = EXPORTER_CLOSE_S,
                 backoff_s: tuple[float, float] = (0.1, 5.0), tls: RelayTls | None = None,
                 spool: Spool | None = None, resume: RunSpool | None = None) -> None:
        if clock not in CLOCKS:
            raise ExportError(f"relay exporter: unknown clock {clock!r} (one of {', '.join(CLOCKS)})")
        self.relays = Failover(url, node, token, backoff_s, tls)
        if not node:
            raise ExportError("relay exporter: the node needs a name")
        self.node = node
        pretend = pretend if pretend is not None else PretendClock(clock_id=CLOCKS[clock])
        if pretend.clock_id != CLOCKS[clock]:
            raise ExportError(f"relay exporter: the pretend clock reads clock {pretend.clock_id}, not {clock}")
        self.close_timeout_s = close_timeout_s
        """How long ``close`` keeps trying every relay for the acknowledgements and ``end``."""
        self.run_id = resume.run if resume is not None else uuid.uuid4().hex
        self.outbox = Outbox(self.run_id, compress=compress, batch_events=batch_events,
                             flush_interval_s=flush_interval_s, adaptive=adaptive, min_flush_s=min_flush_s,
                             max_buffer_events=max_buffer_events, window=window, backoff_s=backoff_s, spool=resume)
        self._spool, self._resumed = spool, resume is not None
        """The spool this run's batches go to (made at start); a drain ships a spooled run."""
        self._end_heard = False
        self.spool_gone = False
        """After close: the run's spool was deleted (everything stored, the end heard)."""
        if resume is not None:
            self.outbox.load_spooled(resume.pending(), resume.next_seq())
        self.clocks = ClockReporter(node, pretend, self.outbox, sync_interval_s=sync_interval_s,
                                    ptp_interval_s=ptp_interval_s, ptp_socket=ptp_socket)
        self._secret: str | None = resume.meta.get("secret") if resume is not None else None
        """The relay's resume secret for this run (its first hello's reply): only with it may a
        connection resume the run."""
        self._header: dict | None = None
        # The loop thread's.
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._connects = 0
        self._connected = False
        self._link: Link | None = None
        self._ended_ns, self._dropped = 0, 0

    @property
    def url(self) -> str:
        """The relay in use: connected, or the one tried next."""
        return self.relays.url

    @property
    def refused(self) -> str | None:
        """Why the relay refused this node (a wrong or missing token), if it did."""
        return self.relays.refused

    # --- Exporter protocol (the probe shipping thread) -----------------------------------

    def start(self, header: TraceHeader) -> None:
        if self._thread is not None:
            raise ExportError("relay exporter already started")
        d = header.to_dict()
        if d["node"] != self.node:
            log.warning("trace header names node %r, shipping it as %r", d["node"], self.node)
            d["node"] = self.node
        self._header = d
        if self._spool is not None and not self._resumed:
            try:
                self.outbox.spool = self._spool.create_run(self.run_id, self.node, d, list(self.relays.urls))
            except SpoolError as exc:
                log.warning("%s; this run's events are kept in memory only", exc)
        ready = threading.Event()
        self._thread = threading.Thread(target=self._thread_main, args=(ready,), daemon=True,
                                         name=f"dcuscope-relay-{self.node}")
        self._thread.start()
        ready.wait(10)

    def write(self, events: np.ndarray) -> None:
        if len(events) and self.outbox.put(events) and self._loop is not None:
            self._loop.call_soon_threadsafe(self._wake.set)

    def close(self, dropped: int, progress: Callable[[int, int], None] | None = None) -> None:
        """Cut what is buffered into batches (local work, at most CUT_WAIT_S), then send them and tell the
        relay the run ended, within ``close_timeout_s``.
        ``progress`` (a drain): first wait while the relay keeps acknowledging, ``close_timeout_s``
        at most without an acknowledgement, calling ``progress(stored, events)`` every CLOSE_SAY_S."""
        if self._thread is None or self._loop is None:
            return
        # Everything written is cut first, whatever the close timeout: a loop still busy spooling when
        # close came (a loaded machine, a slow disk) would otherwise leave the last writes neither
        # spooled nor counted lost.
        try:
            asyncio.run_coroutine_threadsafe(self._cut_pending(), self._loop).result(CUT_WAIT_S)
        except Exception as exc:  # noqa: BLE001 - closing must not raise into the pipeline's teardown
            log.warning("relay exporter %s: close: cutting the last batches: %s", self.node, exc or type(exc).__name__)
        if progress is not None:
            asyncio.run_coroutine_threadsafe(self._until_stalled(progress), self._loop).result()
        deadline = time.monotonic() + self.close_timeout_s
        future = asyncio.run_coroutine_threadsafe(self._finish(int(dropped), deadline), self._loop)
        try:
            future.result(max(0.0, deadline - time.monotonic()))
        except Exception as exc:  # noqa: BLE001 - closing must not raise into the pipeline's teardown
            log.warning("relay exporter %s: close: %s", self.node, exc or type(exc).__name__)
        self._thread.join(max(0.0, deadline - time.monotonic()))
        spool = self.outbox.spool
        if spool is not None:
            if not self._resumed and (spool.events or not self._end_heard):  # run.json counts the spool's own losses
                end = self._end
                spool.set_end({**end, "lost": max(0, end["lost"] - int(spool.meta.get("lost", 0)))})
            self.spool_gone = spool.close(self._end_heard)

    async def _cut_pending(self) -> None:
        if self.outbox.cut():
            self._progress.set()

    async def _until_stalled(self, progress: Callable[[int, int], None]) -> None:
        box = self.outbox
        last, stalled_since, said = box.acked, time.monotonic(), time.monotonic()
        while box.unacked and not self.refused and time.monotonic() - stalled_since < self.close_timeout_s:
            self._progress.clear()
            await wait_event(self._progress, 0.2)
            if box.acked != last:
                last, stalled_since = box.acked, time.monotonic()
            if time.monotonic() - said >= CLOSE_SAY_S:
                said = time.monotonic()
                progress(box.acked, box.written)

    # --- introspection ------------------------------------------------------------------------

    @property
    def lost(self) -> int:
        """Events this node will never deliver (buffer overflow)."""
        return self.outbox.lost

    def delivery(self) -> Delivery:
        """What this run delivered so far (after ``close``: what it delivered)."""
        box = self.outbox
        spool = box.spool
        return Delivery(box.written + box.shed, box.acked, list(self.relays.tried), self.relays.last_error,
                        self.refused, spooled=box.spooled_n if not self.spool_gone else 0,
                        spool_dir=str(spool.spool.path) if spool is not None else "")

    def counters(self) -> dict:
        box = self.outbox
        return {
            "run": self.run_id, "connected": self._connected, "relay": self.url if self._connected else "",
            "connects": self._connects, "batches": box.next_seq,
            "written": box.written, "sent": box.sent, "acked": box.acked, "lost": self.lost,
            "buffered": box.unacked_n + box.pending_n, "pending": box.pending_n,
            "spooled": box.spooled_n if box.spool is not None else None, "retries": box.retries,
            "last_error": self.relays.last_error, "tried": list(self.relays.tried), "clock_via": self.clocks.via,
            "clock_forged": self.clocks.forged,
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

    async def _main(self) -> None:
        tasks = [asyncio.create_task(self.outbox.cut_when_due(self._wake, self._progress, lambda: self._connected)), asyncio.create_task(self.clocks.watch_ptp())]
        try:
            await self.relays.run(self._stop, self._hello, self._on_ack, self._serve)
            await self._stop.wait()
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    def _hello(self) -> dict:
        hello = {"proto": PROTOCOL_VERSION, "run": self.run_id, "header": self._header, **self.outbox.report(),
                 "ptp": self.clocks.ptp}
        if self._resumed:
            hello["spooled"] = True  # a past run drained: not the node's live one
        if self._secret is not None:
            hello["secret"] = self._secret
        return hello

    async def _serve(self, link: Link, hello: dict, reply: dict) -> str:
        """Ship on ``link`` until it ends or the exporter stops; why it ended ("" if it said nothing)."""
        if isinstance(reply.get("secret"), str):
            self._secret = reply["secret"]
            if self.outbox.spool is not None:
                self.outbox.spool.set_secret(self._secret)
        self.outbox.settle_doubts(hello.get("doubt", []), reply)
        self._connects += 1
        self._connected, self._link = True, link
        self._synced.clear()
        self.outbox.resend()
        self._wake.set()  # adaptive batching: an idle link may take what is pending
        workers = [asyncio.create_task(send(link, self.outbox, self._progress)),
                   asyncio.create_task(self.clocks.run(link, self.url, parse_offer(reply), self._synced))]
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
        return link.error or (describe(failed[0]) if failed else "")

    def _on_ack(self, ack: dict) -> None:
        outcome = self.outbox.ack(ack)
        if outcome == "failed":
            # One line while it lasts (no seq in it): every batch fails alike.
            self.relays.note_error(f"relay could not store batches: {str(ack.get('error'))[:100]}; holding them")
        if outcome is not None:
            self._progress.set()
        if outcome == "stored" and self.outbox.adaptive and self.outbox.idle(self._connected):
            self._wake.set()  # what gathered meanwhile may go now

    # --- closing ------------------------------------------------------------------------------

    async def _finish(self, dropped: int, deadline: float) -> None:
        """Wait for the acknowledgements, trying every relay, until ``deadline`` leaves time to say
        ``end``; then say it (to whichever relay answers)."""
        box = self.outbox
        await self._cut_pending()  # anything written after close() cut
        if not self._resumed:
            self._ended_ns, self._dropped = time.time_ns(), dropped
        # What close() keeps to say end and tear down: at most half its time, so that a short
        # close_timeout_s still waits for acknowledgements (or a first answer from the relay).
        reserve = min(END_TIMEOUT_S + TEARDOWN_S, self.close_timeout_s / 2)
        acks_until = deadline - reserve
        await self._await_relay(acks_until, deadline)
        if self._link is not None:
            # A short run still leaves the relay its clock estimate.
            await wait_event(self._synced, max(0.0, acks_until - time.monotonic()))
        link = self._link
        if link is not None and box.doubtful:
            try:
                await self.clocks.send(link, self.clocks.report())
            except (ConnectionError, *ASYNC_TIMEOUTS, aiohttp.ClientError) as exc:
                self.relays.note_error(f"could not ask the relay about doubtful batches: {describe(exc)}")
        for seq in list(box.doubtful):  # not known: counted lost
            box.settle_doubt(seq, False)
        await self._say_end(deadline - reserve * TEARDOWN_S / (END_TIMEOUT_S + TEARDOWN_S))
        self._stop.set()

    async def _await_relay(self, until: float, deadline: float) -> None:
        """Until every batch is acknowledged and a relay is connected (to hear ``end``), or
        ``until``: the connection loop goes on trying every relay meanwhile. What it waits for is
        said every CLOSE_SAY_S."""
        box, said = self.outbox, time.monotonic()
        while (box.unacked or self._link is None) and not self.refused and time.monotonic() < until:
            if time.monotonic() - said >= CLOSE_SAY_S:
                said = time.monotonic()
                what = (f"{box.unacked_n} events to be acknowledged" if box.unacked
                        else "a relay to hear that the run ended")
                where = f"relay {self.url}" if self._connected else f"no relay connected ({self.relays.last_error})"
                log.warning("relay exporter %s: closing: waiting for %s; %s; %.0f s left (--close-timeout)",
                            self.node, what, where, max(0.0, deadline - time.monotonic()))
            self._progress.clear()
            await wait_event(self._progress, min(0.2, max(until - time.monotonic(), 0.01)))

    @property
    def _end(self) -> dict:
        """``end``: the run's events, dropped and lost (not the spooled: they come later), its end time."""
        if self._resumed:
            return self.outbox.spool.end()
        box = self.outbox
        return {"events": box.written, "dropped": self._dropped, "lost": self.lost + box.unacked_n - box.spooled_n,
                "ended_ns": self._ended_ns}

    async def _say_end(self, until: float) -> None:
        """Tell the relay the run ended; a relay lost meanwhile is replaced by the next that answers."""
        while not self.refused and time.monotonic() < until:
            link = self._link
            if link is None:
                await asyncio.sleep(0.1)
                continue
            end = self._end
            try:
                answer = await link.call("end", end, max(0.1, min(END_TIMEOUT_S, until - time.monotonic())))
                self._end_heard = isinstance(answer, dict) and answer.get("ok") is True
                return
            except (ConnectionError, *ASYNC_TIMEOUTS, aiohttp.ClientError) as exc:
                self.relays.note_error(f"could not send end: {describe(exc)}")
                await asyncio.sleep(0.1)
