"""The clock exchanges of one connection to a relay, and the reports that carry them
(:class:`ClockReporter`).

On each connection the node measures the clock offset to the relay and reports the samples with
the node's linuxptp state (``clock``); the relay estimates. The exchanges go over UDP beside the
WebSocket when the relay offers it (:mod:`dcuscope.probes.clocks.udpclock`: kernel timestamps, bursts of
16), else, or when UDP gets no answer, over the WebSocket (``sync``): said once. Over a tagged
exchange (the relay gave a secret) an answer with a wrong tag is refused and counted (``forged``),
and said at most once a minute, naming the relay. A report also tells what the outbox lost and asks
about its doubtful batches (:meth:`dcuscope.probes.ship.outbox.Outbox.report`).
"""

from __future__ import annotations

import asyncio
import logging
import time

from yarl import URL

from dcuscope.core.clocks import PretendClock
from dcuscope.probes.clocks.ptp import PtpWatch
from dcuscope.probes.clocks.udpclock import UdpClock
from dcuscope.probes.ship.aio import describe
from dcuscope.probes.ship.outbox import Outbox
from dcuscope.probes.ship.relaylink import Link
from dcuscope.protocol.clockdatagram import Offer

SYNC_BURST_FIRST, SYNC_BURST = 8, 4
SYNC_TIMEOUT_S = 10.0
UDP_RETRY_S = 30.0
"""After a UDP burst got no answer, the WebSocket exchanges serve this long before UDP is tried again."""
FORGED_SAID_EVERY_S = 60.0

log = logging.getLogger(__name__)


class ClockReporter:
    """Clock samples of node ``node`` read through ``pretend`` (the probes' clock), reported every
    ``sync_interval_s``; the PTP state read from ``ptp_socket`` every ``ptp_interval_s``."""

    def __init__(self, node: str, pretend: PretendClock, outbox: Outbox, *, sync_interval_s: float,
                 ptp_interval_s: float, ptp_socket: str) -> None:
        self._node, self._pretend, self._outbox = node, pretend, outbox
        self._sync_interval, self._ptp_interval = sync_interval_s, ptp_interval_s
        self.ptp: dict = {"state": "unavailable", "reason": "not read yet"}
        self._ptp_watch = PtpWatch(ptp_socket)
        self._udp_failed_at: float | None = None
        self._udp_said = False
        self.via = ""
        """How the last clock samples travelled: udp or websocket."""
        self.forged = 0
        """UDP answers refused for a wrong or missing tag, all connections of the run."""
        self._forged_said_at: float | None = None

    async def watch_ptp(self) -> None:
        while True:
            self.ptp = await self._ptp_watch.read()
            await asyncio.sleep(self._ptp_interval)

    def report(self) -> dict:
        return {**self._outbox.report(), "ptp": self.ptp}

    async def send(self, link: Link, report: dict) -> None:
        """Send a clock report; one that asks about doubtful batches waits for the answer."""
        if "doubt" not in report:
            await link.tell("clock", report)
            return
        reply = await link.call("clock", report, SYNC_TIMEOUT_S)
        if isinstance(reply, dict):
            self._outbox.settle_doubts(report["doubt"], reply)

    async def run(self, link: Link, url: str, offer: Offer | None, synced: asyncio.Event) -> None:
        """Report on ``link`` until cancelled; ``synced`` is set once the relay got a report.
        ``offer``: the UDP exchange the relay offered on this connection."""
        udp = await self._open_udp(url, offer)
        burst = SYNC_BURST_FIRST
        try:
            while True:
                report = self.report()
                samples = await self._udp_burst(udp, offer, url) if udp is not None else []
                if samples:
                    report.update(samples=samples, via="udp")
                else:
                    report["samples"] = await self._ws_burst(link, burst)
                report["forged"] = self.forged
                self.via = report.get("via", "websocket")
                await self.send(link, report)
                synced.set()
                burst = SYNC_BURST
                await asyncio.sleep(self._sync_interval)
        finally:
            if udp is not None:
                udp.close()

    async def _open_udp(self, url: str, offer: Offer | None) -> UdpClock | None:
        if offer is None:
            self._say_once("the relay offers no UDP clock exchange (an older relay, or --clock-port 0)")
            return None
        host = URL(url).host or ""
        try:
            return await UdpClock.open(host, offer.port, offer.key, self._pretend, offer.secret)
        except OSError as exc:
            self._say_once(f"cannot open the UDP clock exchange to {host}:{offer.port}: {describe(exc)}")
            return None

    async def _udp_burst(self, udp: UdpClock, offer: Offer | None, url: str) -> list[list[int]]:
        if self._udp_failed_at is not None and time.monotonic() - self._udp_failed_at < UDP_RETRY_S:
            return []
        forged = udp.forged
        samples = await udp.burst()
        self._count_forged(udp.forged - forged, url)
        if samples:
            self._udp_failed_at = None
            return samples
        self._udp_failed_at = time.monotonic()
        self._say_once(f"no answer to UDP clock exchanges on port {offer.port if offer else '?'} (blocked?)")
        return []

    def _count_forged(self, new: int, url: str) -> None:
        if not new:
            return
        self.forged += new
        now = time.monotonic()
        if self._forged_said_at is None or now - self._forged_said_at >= FORGED_SAID_EVERY_S:
            self._forged_said_at = now
            log.warning("relay exporter %s: UDP clock answers from %s refused for a wrong tag, forged or altered on "
                        "the way (%d so far)", self._node, URL(url).host, self.forged)

    def _say_once(self, why: str) -> None:
        """Falling back to the WebSocket exchange is said once per run, not per connection."""
        if not self._udp_said:
            self._udp_said = True
            log.warning("relay exporter %s: %s; clock samples go over the WebSocket", self._node, why)

    async def _ws_burst(self, link: Link, burst: int) -> list[list[int]]:
        samples = []
        for _ in range(burst):
            t1 = self._pretend.now()
            reply = await link.call("sync", None, SYNC_TIMEOUT_S)
            t4 = self._pretend.now()
            if isinstance(reply, dict) and isinstance(reply.get("t2"), int) and isinstance(reply.get("t3"), int):
                samples.append([t1, reply["t2"], reply["t3"], t4])
        return samples
