"""Which relay a node ships to, and when it moves on (:class:`Failover`).

Several relays (``--relay URL1,URL2``, relays that share one database): the node ships to one at
a time and moves to the next in the list, round robin, when the one it uses cannot be reached
(its TCP connect fails or takes over ``CONNECT_TIMEOUT_S``, its WebSocket handshake over
``HANDSHAKE_TIMEOUT_S``), when its connection drops, when it is silent (the node waits for it,
batches in flight or a request, and hears nothing for ``SILENCE_S``, not even the answer to a
ping: a frozen relay keeps its connections open), or when it answers hello with "later" (``ok:
false`` with ``retry_ms``, e.g. its store fails). A relay that answers that another relay holds
the run is asked again after the wait it gives, for up to ``ELSEWHERE_PATIENCE_S`` (the holder's
lease runs out, or it lets the run go, within seconds), then the next. The next relay is tried at
once; the backoff (exponential, or the wait a relay asked for) runs between rounds, once every
relay of the list failed or asked to come back later. The node never gives up while its run is
open. A relay that refuses the node for now (another live run holds its name) is asked again
after the backoff, as with one relay; a refused token (HTTP 401) ends the tries:
:attr:`Failover.refused` says so (``dcuscope run`` ends with it as its error).
Each move is logged once per outage ("relay URL1 unreachable; trying URL2").
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from typing import Awaitable, Callable, NamedTuple, Sequence

import aiohttp

from dcuscope.core.pycompat import ASYNC_TIMEOUTS
from dcuscope.probes.ship.aio import describe, seconds, wait_event
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.nodetls import RelayTls
from dcuscope.probes.ship.relaylink import ELSEWHERE, Link, Refused, asked_retry_ms, parse_relays

CONNECT_TIMEOUT_S = 2.0
"""A relay whose TCP connect takes longer counts as unreachable: a relay host that is down (its
SYNs unanswered) is left for the next relay within this, not after the whole handshake's bound."""
HELLO_TIMEOUT_S = 10.0
ELSEWHERE_PATIENCE_S = 8.0
"""How long a relay that says another relay holds the run is asked again before the next is tried:
longer than a lease (``relay.store.base.LEASE_S``) plus the time a relay takes to see its node gone
(``protocol.wire.SILENCE_S``)."""

UNREACHABLE, REFUSED, LATER, ELSEWHERE_HOLDS = "unreachable", "refused", "later", "elsewhere"

log = logging.getLogger(__name__)

Serve = Callable[[Link, dict, dict], Awaitable[str]]
"""Ships on a link that said hello (the hello sent, the relay's reply) until it ends; why it ended."""


class Miss(NamedTuple):
    """Why a connection attempt gave no link: the relay could not be reached, refused this node
    (for now, or its token: :attr:`Failover.refused`), asked it to come back later (after
    ``wait_s``, if it said), or said that another relay holds its run."""

    kind: str
    why: str
    wait_s: float | None = None


class Failover:
    """The relays of ``urls`` (see :func:`dcuscope.probes.ship.relaylink.parse_relays`) for node ``node``:
    which one is in use, when to try the next, and what is said meanwhile."""

    def __init__(self, urls: str | Sequence[str], node: str, token: str | None,
                 backoff_s: tuple[float, float] = (0.1, 5.0), tls: RelayTls | None = None) -> None:
        self.urls = parse_relays(urls)
        self._ssl = tls.context() if tls is not None else True
        """How https:// relays are verified (True: against the system's CAs; ``tls``: its CAs, its certificate)."""
        self.url = self.urls[0]
        """The relay of ``urls`` in use: connected, or the one tried next."""
        self._node, self._token, self._backoff = node, token, backoff_s
        self.last_error = ""
        self.tried: list[str] = []
        """The relays of ``urls`` tried so far, in the order first tried (the node's summary names them)."""
        self.refused: str | None = None
        """Why the relay refused this node (a wrong or missing token), if it did."""
        self._moves_said: set[tuple[str, str, str]] = set()
        """Moves to another relay logged since the last hello: each said once per outage."""
        self._elsewhere_since: float | None = None
        """When the relay in use first answered that another relay holds the run (None: it did not)."""

    def note_error(self, message: str) -> None:
        if message != self.last_error:
            log.warning("relay exporter %s: %s", self._node, message)
        self.last_error = message

    async def run(self, stop: asyncio.Event, hello: Callable[[], dict], on_ack: Callable[[dict], None],
                  serve: Serve) -> None:
        """Connect, say ``hello()``, ``serve``, and again on the next relay, until ``stop`` is set
        (or the token is refused)."""
        delay = self._backoff[0]
        misses = 0  # relays in a row that could not be reached
        laters = 0  # relays in a row that asked to come back later
        # total=None: the handshake has its own bound (relaylink), and the WebSocket lives on.
        timeout = aiohttp.ClientTimeout(total=None, sock_connect=CONNECT_TIMEOUT_S)
        async with aiohttp.ClientSession(timeout=timeout, connector=aiohttp.TCPConnector(ssl=self._ssl)) as session:
            while not stop.is_set():
                outcome = await _unless(stop, self._connect(session, hello, on_ack))
                if self.refused:
                    break  # no use asking again: close() reports it
                if outcome is None:
                    continue  # stopped
                if not isinstance(outcome, Miss):
                    delay, misses, laters = self._backoff[0], 0, 0
                    self._elsewhere_since = None
                    self._moves_said.clear()
                    why = await serve(*outcome)
                    if not stop.is_set():
                        self._move_on(f"connection to relay {self.url} lost", why)
                    continue
                if outcome.kind == ELSEWHERE_HOLDS and self._patient():
                    misses = 0
                    # The run's holder lets it go (its node left it) or its lease runs out: this relay takes it then.
                    wait = min(outcome.wait_s, self._backoff[1]) if outcome.wait_s is not None else delay
                    self.note_error(f"relay {self.url}: another relay holds this run; asking again")
                elif outcome.kind in (LATER, ELSEWHERE_HOLDS):
                    misses, laters = 0, laters + 1
                    self._elsewhere_since = None
                    # The next relay at once (its store may work); once every relay asked, as long as
                    # the last asks, within the backoff's cap.
                    asked = min(outcome.wait_s, self._backoff[1]) if outcome.wait_s is not None else delay
                    wait = asked if laters % len(self.urls) == 0 else 0.0
                    self._move_on(f"relay {self.url} asks to come back later", outcome.why, wait)
                elif outcome.kind == REFUSED:
                    misses, wait = 0, delay
                    self.note_error(f"relay {self.url} refused this node for now: {outcome.why}")
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
                    await wait_event(stop, wait)

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
            self.note_error(f"{what}: {why}" if why else what)
            return
        previous = self.url
        self.url = self.urls[(self.urls.index(previous) + 1) % len(self.urls)]
        then = f" in {wait_s:.1f} s" if wait_s else ""
        self.last_error = f"{what}; trying {self.url}{then}" + (f" ({why})" if why else "")
        # Said once per outage: while no relay answers, the node goes round the list quietly.
        if (previous, self.url, what) not in self._moves_said:
            self._moves_said.add((previous, self.url, what))
            log.warning("relay exporter %s: %s", self._node, self.last_error)

    async def _connect(self, session: aiohttp.ClientSession, make_hello: Callable[[], dict],
                       on_ack: Callable[[dict], None]) -> tuple[Link, dict, dict] | Miss:
        """A link that said hello (``make_hello()`` once connected), with the hello and the relay's
        reply; or why not."""
        if self.url not in self.tried:
            self.tried.append(self.url)
        try:
            link = await Link.open(session, self.url, self._token, on_ack)
        except Refused as exc:
            # Not logged: the run ends with this as its one error line (probes.instrument).
            self.refused = self.last_error = str(exc)
            return Miss(REFUSED, str(exc))
        except ExportError as exc:
            return Miss(UNREACHABLE, str(exc))
        hello = make_hello()
        try:
            reply = await link.call("hello", hello, HELLO_TIMEOUT_S)
        except (ConnectionError, *ASYNC_TIMEOUTS, aiohttp.ClientError) as exc:
            await link.close()
            if link.elsewhere:  # another relay holds the run: not a refusal of this node
                return Miss(ELSEWHERE_HOLDS, link.error, seconds(link.retry_ms))
            if link.error.startswith("relay error"):
                # The relay said why (e.g. another live run holds this node's name): it is asked again later.
                return Miss(REFUSED, link.error)
            return Miss(UNREACHABLE, link.error or describe(exc))
        if not (isinstance(reply, dict) and reply.get("ok")):
            # A relay that cannot take the run now (it says for how long, with retry_ms).
            await link.close()
            error = str(reply.get("error") if isinstance(reply, dict) else "")
            kind = ELSEWHERE_HOLDS if ELSEWHERE.search(error) else LATER
            return Miss(kind, f"relay refused hello: {str(reply)[:200]}", seconds(asked_retry_ms(reply)))
        return link, hello, reply


async def _unless(stop: asyncio.Event, attempt: Awaitable):
    """The attempt's result, or None if ``stop`` was set first (close() must not wait out a
    handshake with a relay that does not answer)."""
    connecting = asyncio.ensure_future(attempt)
    stopping = asyncio.create_task(stop.wait())
    await asyncio.wait([connecting, stopping], return_when=asyncio.FIRST_COMPLETED)
    stopping.cancel()
    if connecting.done():
        return connecting.result()
    connecting.cancel()
    await asyncio.gather(connecting, return_exceptions=True)
    return None
