"""A node's end of one ingest WebSocket (``GET /ingest``): requests with replies, batches with
acknowledgements, in the envelope of :mod:`dcuscope.protocol.envelope`.

    link = await Link.open(session, "http://127.0.0.1:3000", token, on_ack)
    reply = await link.call("hello", {...}, timeout=10)
    await link.send_batch(encode_batch(...))       # on_ack(message) once the relay stored it
    await link.closed()                            # the connection ended (link.error says why)

``--relay`` names one relay or several (:func:`parse_relays`); the node ships to one at a time
(:class:`dcuscope.probes.ship.relayexport.RelayExporter` moves on when one cannot serve it).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import re
import time
import urllib.error
import urllib.request
from typing import Callable, Sequence

import aiohttp
from aiohttp import WSMsgType

from dcuscope.core.pycompat import ASYNC_TIMEOUTS, timeout as deadline
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.nodetls import RelayTls, tls_failure
from dcuscope.protocol import envelope
from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.wire import INGEST_PATH, MAX_MESSAGE_BYTES

HANDSHAKE_TIMEOUT_S = 5.0
"""A relay that has not completed the WebSocket handshake within this is unreachable (a frozen
relay's kernel still accepts the TCP connection: only the handshake tells)."""
CLOSE_TIMEOUT_S = 1.0
ELSEWHERE = re.compile(r"\b(owned by|another relay)\b", re.IGNORECASE)
"""An error the relay closes a hello with when another relay of the fleet holds the run: not a
refusal of this node, which is to come back later (to whichever relay then holds it)."""


class Refused(ExportError):
    """The relay refused the node before the WebSocket opened (a wrong or missing token)."""


def parse_relays(relays: str | Sequence[str]) -> tuple[str, ...]:
    """The relays ``--relay`` names: one URL, several separated by commas, or a list of them;
    each ``http[s]://HOST:PORT``, returned without a trailing slash. :class:`ExportError` names
    the item at fault."""
    items = relays.split(",") if isinstance(relays, str) else list(relays)
    urls = []
    for i, item in enumerate(items, 1):
        url = item.strip() if isinstance(item, str) else item
        if not url:
            raise ExportError(f"relay list {relays!r}: item {i} is empty" if len(items) > 1
                              else "the relay URL is empty")
        if not isinstance(url, str) or not url.startswith(("http://", "https://")):
            raise ExportError(f"relay URL must start with http:// or https://, not {url!r}")
        urls.append(url.rstrip("/"))
    return tuple(urls)


def check_token(relays: str | Sequence[str], token: str | None, timeout_s: float = 3.0,
                tls: RelayTls | None = None) -> None:
    """Raise :class:`Refused` if a relay of ``relays`` (:func:`parse_relays`) refuses ``token``,
    before a run starts; :class:`ExportError` if one is no relay URL.

    A plain GET of the ingest path is answered 401 for a wrong token before anything else.
    A relay that does not answer passes: the exporter keeps trying, and loses nothing. Every
    relay of a list is asked, one after the other: the node may land on any of them. So does one
    that fails TLS: the exporter says why, and moves on.
    """
    context = (tls or RelayTls()).context()
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    for url in parse_relays(relays):
        try:
            request = urllib.request.Request(url + INGEST_PATH, headers=headers)
            urllib.request.urlopen(request, timeout=timeout_s, context=context).close()
        except urllib.error.HTTPError as exc:
            if exc.code == 401:
                raise Refused(f"relay {url} refused the token (HTTP 401{_said(exc)})") from None
        except (OSError, ValueError):
            pass


def _said(exc: urllib.error.HTTPError) -> str:
    """The relay's reason in a refusal's body (``{"error": ...}``), as ``": REASON"``; "" if none."""
    try:
        reason = json.loads(exc.read(2000)).get("error")
    except (OSError, ValueError, AttributeError):
        return ""
    return f": {reason[:200]}" if isinstance(reason, str) and reason.isprintable() else ""


class Link:
    def __init__(self, ws: aiohttp.ClientWebSocketResponse, on_ack: Callable[[dict], None]) -> None:
        self.ws = ws
        self.error = ""
        """Why the relay ended the connection, when it said so."""
        self.retry_ms: int | None = None
        """How long the relay asked the node to wait before it comes back, with its error."""
        self._on_ack = on_ack
        self.heard_at = time.monotonic()
        """When the relay last sent anything (a message, a ping, a pong; monotonic)."""
        self._pinged_at = float("-inf")
        self.asked_at: float | None = None
        """Since when a request has been waiting for its reply (None: none waits; monotonic)."""
        self._calls: dict[int, asyncio.Future] = {}
        self._ids = itertools.count()
        self._reader = asyncio.create_task(self._read())

    @classmethod
    async def open(cls, session: aiohttp.ClientSession, url: str, token: str | None,
                   on_ack: Callable[[dict], None]) -> "Link":
        """Connect to the relay at ``url`` (http[s]://HOST:PORT). Raises :class:`Refused` for an
        HTTP 401, :class:`ExportError` for any other failure to connect."""
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        ws_url = "ws" + url[len("http"):] + INGEST_PATH
        try:
            async with deadline(HANDSHAKE_TIMEOUT_S):
                # Pings and pongs are read here (autoping off): a pong counts as the relay heard from.
                ws = await session.ws_connect(ws_url, headers=headers, autoping=False,
                                              max_msg_size=MAX_MESSAGE_BYTES,
                                              timeout=aiohttp.ClientWSTimeout(ws_close=CLOSE_TIMEOUT_S))
        except aiohttp.WSServerHandshakeError as exc:
            if exc.status == 401:
                raise Refused(f"relay {url} refused the token (HTTP 401)") from exc
            if exc.status == 403 and url.startswith("https://"):
                raise ExportError(f"HTTP 403 {exc.message}: the relay wants a client certificate it trusts, "
                                  "naming this node (--relay-cert)") from exc
            raise ExportError(f"HTTP {exc.status} {exc.message}") from exc
        except (aiohttp.ClientError, OSError, *ASYNC_TIMEOUTS) as exc:
            why = tls_failure(exc)
            if why is None and url.startswith("https://") and dropped_after_handshake(exc):
                # A relay that fails a client certificate's handshake closes without an alert
                # (asyncio's TLS transport aborts): TLS 1.3 tells the client only then.
                why = ("TLS: the relay closed the connection after the handshake: it refuses this node's "
                       "certificate, or wants one (--relay-cert)")
            raise ExportError(why or str(exc) or type(exc).__name__) from exc
        return cls(ws, on_ack)

    async def call(self, kind: str, data: object, timeout: float) -> object:
        """Send a request and wait for its reply's data (ConnectionError if the link ends first)."""
        ident = next(self._ids)
        future = asyncio.get_running_loop().create_future()
        if not self._calls:
            self.asked_at = time.monotonic()
        self._calls[ident] = future
        try:
            await self.ws.send_str(envelope.request(kind, data, ident))
            async with deadline(timeout):
                return await future
        finally:
            self._calls.pop(ident, None)
            if not self._calls:
                self.asked_at = None

    async def tell(self, kind: str, data: object) -> None:
        """Send a message that wants no reply."""
        await self.ws.send_str(envelope.request(kind, data))

    async def send_batch(self, data: bytes) -> None:
        await self.ws.send_bytes(data)

    def silent_s(self, since: float) -> float:
        """How long the relay has said nothing, counted from ``since`` at the earliest (monotonic)."""
        return time.monotonic() - max(self.heard_at, since)

    async def ping(self) -> None:
        """Ask the relay for a sign of life (its pong), once per silence."""
        if self._pinged_at < self.heard_at:
            self._pinged_at = time.monotonic()
            await self.ws.ping()

    async def closed(self) -> None:
        await asyncio.shield(self._reader)

    async def close(self) -> None:
        """Close the WebSocket, its handshake given ``2 * CLOSE_TIMEOUT_S`` at most. A connection that
        cannot take even the close frame (a cut path: TCP holds what was sent, the socket's buffers are
        full) is aborted, or its socket and buffers would stay until TCP's own timeout, many minutes."""
        self._reader.cancel()
        # aiohttp lets go of the connection as the close fails: its transport is taken first
        connection = self.ws._response.connection
        transport = connection.transport if connection is not None else None
        try:
            async with deadline(2 * CLOSE_TIMEOUT_S):
                await self.ws.close()
        except (aiohttp.ClientError, OSError, *ASYNC_TIMEOUTS):  # a half-open connection
            if transport is not None:
                transport.abort()

    async def _read(self) -> None:
        try:
            async for msg in self.ws:
                self.heard_at = time.monotonic()
                if msg.type == WSMsgType.PING:
                    await self.ws.pong(msg.data)
                    continue
                if msg.type == WSMsgType.PONG:
                    continue
                if msg.type != WSMsgType.TEXT:
                    self.error = f"relay sent a {msg.type.name} frame"
                    break
                self._dispatch(envelope.decode_reply(msg.data))
        except ProtocolError as exc:
            self.error = f"relay sent {exc}"
        finally:
            for future in self._calls.values():
                if not future.done():
                    future.set_exception(ConnectionError(self.error or "connection to the relay closed"))
            if not self.error and self.ws.close_code not in (None, 1000):
                self.error = f"relay closed the connection ({self.ws.close_code})"

    def _dispatch(self, d: dict) -> None:
        if d["type"] == "reply":
            ident = d.get("id")
            future = self._calls.get(ident) if isinstance(ident, int) else None
            if future is not None and not future.done():
                future.set_result(d.get("data"))
        elif d["type"] == "ack":
            self._on_ack(d)
        else:
            self.error = f"relay error: {str(d.get('error'))[:200]}"
            self.retry_ms = asked_retry_ms(d)

    @property
    def elsewhere(self) -> bool:
        """The relay closed the connection because another relay holds this node's run."""
        return self.error.startswith("relay error") and ELSEWHERE.search(self.error) is not None


def dropped_after_handshake(exc: BaseException) -> bool:
    """Whether the relay closed the connection once connected, before answering the upgrade."""
    return (isinstance(exc, (aiohttp.ServerDisconnectedError, aiohttp.ClientOSError, ConnectionResetError))
            and not isinstance(exc, aiohttp.ClientConnectorError))


def asked_retry_ms(d: object) -> int | None:
    """The ``retry_ms`` a relay's message asks for (a positive integer), else None."""
    asked = d.get("retry_ms") if isinstance(d, dict) else None
    return asked if isinstance(asked, int) and not isinstance(asked, bool) and asked > 0 else None
