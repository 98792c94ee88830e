"""Every relay's pushes to every browser: python-socketio's Redis manager (``--redis URL``).

With ``--redis redis://HOST:PORT/N`` the relay's Socket.IO server uses python-socketio's
:class:`socketio.AsyncRedisManager`, as python-socketio documents for servers that scale out: an
emit is delivered to this relay's own browsers at once and published on a Redis channel, from
which every other relay delivers it to its browsers. Relays sharing a store then show every DCU of
the fleet on every page. Without ``--redis`` the stock in-process manager serves this relay's
browsers only (one relay, or relays whose pages need only their own DCUs).

Pushes are routed by room, not broadcast: python-socketio's manager publishes every emit on one
channel, so every relay would receive and decode every other relay's pushes, whether or not a
browser of its own shows those DCUs (with 4 relays, most of each one's CPU). Here an emit to a room
(``dcu:25:DCU-7``, ``every-dcu:25``, ``overview``, a browser's own) goes on that room's channel
(``dcuscope:room:ROOM``), and a relay subscribes to the channels of the rooms its own browsers are
in, as they join and leave: it receives only what its browsers show. Everything else the manager
says to the other relays (a room's members, disconnects, callbacks) stays on ``CHANNEL``. Each
message starts with its sender's id, so a relay skips its own (it already delivered them) without
decoding them. An emit to a room is delivered to this relay's browsers straight away (python-socketio's
manager encodes it for Redis first, then decodes it again for them), and one whose channel had no
listener (PUBLISH's answer) is not even encoded for Redis for ``DEAF_S``: a relay whose DCUs no other
relay's page shows publishes nothing of its pushes.

**Forwarded as bytes.** An emit to a room is encoded once, as the Socket.IO packet its browsers get
(its text part and its binary attachments, the pushed columns), and that packet goes on the room's
channel as it is (:func:`forward_message`): a relay that receives it hands the same bytes to its own
browsers in that room, with no JSON, base64 or Socket.IO encoding per push and no work per frame
(python-socketio's own manager would publish JSON with base64 attachments, decode it on every relay
and encode it again there). What python-socketio itself says on ``CHANNEL`` stays its JSON.

Redis is not needed for anything but those pushes. While it is down or restarting:

- ingest and storage go on untouched (they never touch Redis);
- this relay's own browsers keep their pushes (delivered locally before publishing);
- publishing is skipped (not retried, not queued): other relays' browsers miss this relay's pushes
  and catch up from the store when it returns (the page backfills the frames it missed);
- the subscriber reconnects every ``RETRY_S``, not with python-socketio's backoff of up to a
  minute, so pushes resume within a second of Redis' return;
- ``/api/health``'s ``fanout`` says so, and the log has one line per change (python-socketio's own
  line per failed attempt is held back).

``redis+sentinel://S1:26379,S2:26379/DB/SERVICE`` names Redis Sentinels instead of a Redis: every
connection asks them for the master of SERVICE (python-socketio's and redis-py's own support), so a
master that dies and is replaced by a promoted replica is followed within ``RETRY_S`` of the
promotion (docs/store-failover.md).

``rediss://`` is Redis over TLS: the server's certificate is checked against the system's CAs, or
those of ``--redis-ca FILE`` (:func:`check_url`), and its name against the URL's host. A certificate
that fails the check is a Redis that cannot be reached: one line in the log, ``fanout.error`` says why.
"""

from __future__ import annotations

import asyncio
import json
import logging
import struct
import time
from urllib.parse import urlencode, urlsplit, urlunsplit

import socketio
from engineio import packet as eio_packet
from socketio import packet as sio_packet
from socketio.redis_manager import parse_redis_sentinel_url

from dcuscope.core.clocks import NEVER
from dcuscope.relay.errors import RelayError
from dcuscope.relay.urls import redact

SENTINEL = "redis+sentinel"
CHANNEL = "dcuscope"
"""The Redis channel the relays' Socket.IO servers share (python-socketio's ``channel``)."""
ROOM_CHANNEL = CHANNEL + ":room:"
"""Followed by a room's name: the channel of the emits to that room."""
RETRY_S = 1.0
TIMEOUT_S = 1.0
"""Connecting to Redis and publishing give up after this long (a Redis that stopped answering)."""
QUIET = ("Cannot publish to redis", "Cannot receive from redis")
FORWARD = b"\x00dcuscope-forward-1\n"
"""How a forwarded packet's message starts (after its sender's id): a JSON text never does."""
TEXT, BINARY = b"T", b"B"
PART = struct.Struct("<cI")
"""Each part of a forwarded packet: its kind (TEXT or BINARY) and its length, then its bytes."""
DEAF_S = 0.25
"""A room channel no relay listened to is not published to for this long (a relay whose page just
joined that room misses at most this much, which the page fills from GET /api/frames)."""

log = logging.getLogger(__name__)


def check_url(url: str, ca: str | None = None) -> str:
    """``url`` if it names a Redis server python-socketio can use; RelayError saying why not otherwise.
    ``ca`` (``--redis-ca``): the file of the CAs that a ``rediss://`` server's certificate must come
    from, put in the URL as redis-py's ``ssl_ca_certs`` parameter, so that every connection made from
    the URL (python-socketio's manager, :mod:`dcuscope.relay.api.interest`) checks it; without it, the URL's own
    ``ssl_ca_certs``, else the system's CAs."""
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme not in ("redis", "rediss", "unix", SENTINEL):
        raise RelayError(f"--redis {redact(url)!r}: not a Redis URL (redis://HOST:PORT/DB, rediss://, unix://, "
                         f"{SENTINEL}://HOST:PORT[,HOST:PORT...]/DB/SERVICE)")
    if scheme == SENTINEL:
        try:
            _, service, _ = parse_redis_sentinel_url(url)
        except ValueError as exc:
            raise RelayError(f"--redis {redact(url)!r}: cannot read the sentinels ({exc}): give each as HOST:PORT, "
                             f"{SENTINEL}://HOST:PORT[,HOST:PORT...]/DB/SERVICE") from None
        if service is None:
            raise RelayError(f"--redis {redact(url)!r}: name the Sentinels' service: {SENTINEL}://HOST:PORT/DB/SERVICE")
    if ca is None:
        return url
    if scheme != "rediss":
        raise RelayError(f"--redis-ca checks a TLS server's certificate: give a rediss:// URL, not {redact(url)!r}")
    try:
        open(ca, "rb").close()
    except OSError as exc:
        raise RelayError(f"--redis-ca {ca}: {exc.strerror}") from None
    query = "&".join(q for q in (parts.query, urlencode({"ssl_ca_certs": ca}, safe="/")) if q)
    return urlunsplit(parts._replace(query=query))


def redis_client(url: str, **options):
    """An asyncio Redis client of ``url`` (as :func:`check_url` returned it): a Sentinel URL's follows
    the master of its service, as python-socketio's manager does."""
    from redis import asyncio as aioredis

    if urlsplit(url).scheme.lower() != SENTINEL:
        return aioredis.Redis.from_url(url, **options)
    sentinels, service, kwargs = parse_redis_sentinel_url(url)
    return aioredis.sentinel.Sentinel(sentinels, **options, **kwargs).master_for(service)


class FanoutHealth:
    """Whether pushes reach the other relays now; one log line per change."""

    def __init__(self, mode: str, url: str | None = None) -> None:
        self.mode = mode
        self.url = redact(url) if url else None
        self.ok = mode == "local"
        self.since = time.time()
        self.error: str | None = None if self.ok else "not connected yet"
        self.outages = 0
        self.received = 0
        """Messages of other relays this relay received (their pushes to rooms its browsers are in)."""
        self.rooms = 0
        """Room channels this relay listens to now."""
        self._told_down = False

    def up(self) -> None:
        if not self.ok:
            self.ok, self.since, self.error, self._told_down = True, time.time(), None, False
            log.warning("redis %s: connected; this relay's pushes reach every relay's browsers", self.url)

    def down(self, error: str) -> None:
        if self.ok:
            self.outages += 1
            self.since = time.time()
        if not self._told_down:
            self._told_down = True
            log.warning("redis %s: %s; only this relay's browsers get its pushes (other relays' catch up from "
                        "the store when it returns)", self.url, error)
        self.ok, self.error = False, error

    def view(self) -> dict:
        return {"mode": self.mode, "url": self.url, "ok": self.ok, "since": self.since, "error": self.error,
                "outages": self.outages, "received": self.received, "rooms": self.rooms}


class FleetManager(socketio.AsyncRedisManager):
    """python-socketio's Redis manager, degrading as the module's docstring says."""

    def __init__(self, url: str, health: FanoutHealth) -> None:
        super().__init__(check_url(url), channel=CHANNEL, logger=_quiet_logger(),
                         redis_options={"socket_connect_timeout": TIMEOUT_S, "health_check_interval": 5})
        self.health = health
        self._subscribed: set[str] = set()
        """Room channels the subscriber listens to now (those of the rooms this relay's browsers are in)."""
        self._resubscribe = asyncio.Event()
        self._deaf: dict[str, float] = {}
        """Room channels no other relay listened to at the last publish -> until when they are skipped."""

    async def _publish(self, data):
        """What python-socketio's manager says to the other relays (its JSON), on ``CHANNEL``."""
        return await self._send(self.channel, (self.host_id + self.json.dumps(data)).encode())

    async def _send(self, channel: str, message: bytes):
        if not self.health.ok:
            return None  # the subscriber finds Redis back; until then other relays catch up from the store
        try:
            got = await asyncio.wait_for(self.redis.publish(channel, message), TIMEOUT_S)
            if channel != self.channel:
                if got:
                    self._deaf.pop(channel, None)
                else:
                    self._deaf[channel] = time.monotonic() + DEAF_S
            return got
        except Exception as exc:  # noqa: BLE001 - any failure of Redis: degrade, say it once
            self.health.down(f"cannot publish: {_describe(exc)}")
            # The subscriber's connection goes too: it reconnects, and says when Redis is back.
            await self._close_connections()
            return None

    async def emit(self, event, data, namespace=None, room=None, skip_sid=None, callback=None, to=None, **kwargs):
        room = to or room
        if callback is not None or kwargs.get("ignore_queue") or not isinstance(room, str):
            return await super().emit(event, data, namespace=namespace, room=room, skip_sid=skip_sid,
                                      callback=callback, **kwargs)
        namespace = namespace or "/"
        args = list(data) if isinstance(data, tuple) else [] if data is None else [data]  # as python-socketio's emit
        parts = self.server.packet_class(sio_packet.EVENT, namespace=namespace, data=[event, *args]).encode()
        parts = parts if isinstance(parts, list) else [parts]
        await self._deliver(parts, namespace, room, skip_sid)
        channel = ROOM_CHANNEL + room
        if self._deaf.get(channel, NEVER) > time.monotonic():
            return None  # no other relay listened a moment ago: not sent
        await self._send(channel, self.host_id.encode() + forward_message(namespace, room, skip_sid, parts))
        return None

    async def _deliver(self, parts: list, namespace: str, room: str, skip_sid) -> None:
        """A Socket.IO packet, encoded (``parts``), to this relay's browsers in ``room``: what python-socketio's
        emit does once it encoded a packet."""
        if namespace not in self.rooms:
            return
        skip = skip_sid if isinstance(skip_sid, list) else [skip_sid]
        packets = [eio_packet.Packet(eio_packet.MESSAGE, p) for p in parts]
        tasks = [asyncio.create_task(self.server._send_eio_packet(eio_sid, p))
                 for sid, eio_sid in self.get_participants(namespace, room) if sid not in skip for p in packets]
        if tasks:
            await asyncio.wait(tasks)

    # --- the room channels this relay listens to ---------------------------------------------------

    def _wanted_channels(self) -> set[str]:
        return {ROOM_CHANNEL + room for rooms in self.rooms.values() for room in rooms if isinstance(room, str)}

    async def enter_room(self, sid, namespace, room, eio_sid=None):
        await super().enter_room(sid, namespace, room, eio_sid)
        self._resubscribe.set()

    async def leave_room(self, sid, namespace, room):
        await super().leave_room(sid, namespace, room)
        self._resubscribe.set()

    async def disconnect(self, sid, namespace, **kwargs):
        await super().disconnect(sid, namespace, **kwargs)
        self._resubscribe.set()

    async def _follow_rooms(self, pubsub) -> None:
        """Keep ``pubsub`` subscribed to the channels of the rooms this relay's browsers are in."""
        while True:
            await self._resubscribe.wait()
            self._resubscribe.clear()
            wanted = self._wanted_channels()
            if wanted - self._subscribed:
                await pubsub.subscribe(*(wanted - self._subscribed))
            if self._subscribed - wanted:
                await pubsub.unsubscribe(*(self._subscribed - wanted))
            self._subscribed = wanted
            self.health.rooms = len(wanted)

    async def _redis_listen_with_retries(self):
        while True:
            follow = None
            try:
                self._redis_connect()
                self._subscribed = set()
                await asyncio.wait_for(self.pubsub.subscribe(self.channel), TIMEOUT_S)
                self._resubscribe.set()
                follow = asyncio.create_task(self._follow_rooms(self.pubsub))
                self.health.up()
                async for message in self.pubsub.listen():
                    if follow.done():  # subscribing failed: Redis is failing
                        follow.result()
                    yield message
                raise ConnectionError("subscription ended")
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - any failure of Redis: degrade, retry
                self.health.down(f"cannot receive: {_describe(exc)}")
                await self._close_connections()
                await asyncio.sleep(RETRY_S)
            finally:
                if follow is not None:
                    follow.cancel()

    async def _listen(self):
        me = self.host_id.encode()
        base, rooms = self.channel.encode(), ROOM_CHANNEL.encode()
        async for message in self._redis_listen_with_retries():
            channel, data = message.get("channel", b""), message.get("data")
            if (message.get("type") != "message" or not isinstance(data, bytes)
                    or not (channel == base or channel.startswith(rooms))):
                continue
            sender, body = data[:len(me)], data[len(me):]
            if sender == me:  # this relay delivered its own to its browsers already
                continue
            self.health.received += 1
            if not body.startswith(FORWARD):
                yield body  # python-socketio's own
                continue
            try:
                await self._deliver(*read_forward(body))
            except ValueError as exc:  # not what a relay sends: said, and dropped
                log.warning("redis: a forwarded packet dropped: %s", exc)

    async def close(self) -> None:
        """Stop the subscriber and close the connections (the relay stops)."""
        task = getattr(self, "thread", None)
        if isinstance(task, asyncio.Task):
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        await self._close_connections()

    async def _close_connections(self) -> None:
        for conn in (self.pubsub, self.redis):
            if conn is not None:
                try:
                    await conn.aclose()
                except Exception:  # noqa: BLE001 - Redis may be gone already
                    pass
        self.pubsub = self.redis = None
        self.connected = False


def forward_message(namespace: str, room: str, skip_sid, parts: list) -> bytes:
    """A Socket.IO packet, as ``encode()`` gave it (a text part, then binary attachments), for the room's
    channel: :data:`FORWARD`, a JSON line (namespace, room, skip_sid), then each part."""
    head = json.dumps({"namespace": namespace, "room": room, "skip_sid": skip_sid}).encode()
    out = [FORWARD, head, b"\n"]
    for part in parts:
        raw = part.encode() if isinstance(part, str) else bytes(part)
        out += [PART.pack(TEXT if isinstance(part, str) else BINARY, len(raw)), raw]
    return b"".join(out)


def read_forward(message: bytes) -> tuple[list, str, str, object]:
    """(parts, namespace, room, skip_sid) of a :func:`forward_message`; ValueError saying why it is not one."""
    if not message.startswith(FORWARD):
        raise ValueError("not a forwarded packet")
    at = message.find(b"\n", len(FORWARD))
    if at < 0:
        raise ValueError("no header line")
    try:
        head = json.loads(message[len(FORWARD):at])
        namespace, room, skip_sid = head["namespace"], head["room"], head["skip_sid"]
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f"bad header: {exc}") from None
    if not isinstance(namespace, str) or not isinstance(room, str):
        raise ValueError("bad header: namespace and room must be strings")
    parts, at = [], at + 1
    while at < len(message):
        if at + PART.size > len(message):
            raise ValueError("a part's header cut short")
        kind, size = PART.unpack_from(message, at)
        at += PART.size
        if kind not in (TEXT, BINARY) or at + size > len(message):
            raise ValueError("a part of an unknown kind or cut short")
        raw = message[at:at + size]
        parts.append(raw.decode() if kind == TEXT else raw)
        at += size
    if not parts or not isinstance(parts[0], str):
        raise ValueError("no text part first")
    return parts, namespace, room, skip_sid


def create_manager(url: str | None) -> tuple[socketio.AsyncManager | None, FanoutHealth]:
    """The Socket.IO client manager for ``--redis`` (None: python-socketio's in-process one), and its health."""
    if url is None:
        return None, FanoutHealth("local")
    health = FanoutHealth("redis", url)
    return FleetManager(url, health), health


class _Quiet(logging.Filter):
    """python-socketio's manager logs every failed attempt; FanoutHealth says each change once."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(QUIET)


def _quiet_logger() -> logging.Logger:
    logger = logging.getLogger("dcuscope.relay.fanout.redis")
    if not any(isinstance(f, _Quiet) for f in logger.filters):
        logger.addFilter(_Quiet())
    return logger


def _describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text[:200]}" if text else type(exc).__name__
