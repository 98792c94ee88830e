"""The browsers' Socket.IO server (namespace ``/ui``), made with public python-socketio options.

Only browsers speak Socket.IO here (nodes use the plain WebSocket of :mod:`dcuscope.relay.ingest.endpoint`), and
they only listen and ``subscribe``. What a client that sends garbage could still cause is
logged tracebacks: python-socketio and python-engineio log an exception for a packet they
cannot parse, and aiohttp one for a request handler that raises. The loggers handed to the
server write such a failure as one line, and :func:`sio_errors` ends the request of a
handler that raised with a one-line log instead of aiohttp's traceback.
"""

from __future__ import annotations

import logging

import socketio
from aiohttp import web
from socketio import packet as sio_packet

SIO_PATH = "/socket.io/"
MAX_UI_MESSAGE_BYTES = 64 * 1024
"""Browsers send only ``subscribe``."""

log = logging.getLogger(__name__)


class JsonPacket(sio_packet.Packet):
    """Socket.IO packets of the relay, which sends binary only as values of objects (the packed
    frames of a push, :mod:`dcuscope.relay.live.framepack`).

    The stock packet walks every list and dict of an outgoing message looking for bytes to send as
    attachments, and copies each while it takes them out; through the lists of a big message
    (statistics, a fleet's rows, a push's field layouts) that walk costs more than making it: 3/4
    of a frames push's encoding (~700 calls for 8 DCUs). Here only objects are walked, and the
    lists at the top, to find them and to take them out.
    """

    @classmethod
    def data_is_binary(cls, data) -> bool:
        if isinstance(data, (bytes, bytearray)):
            return True
        if isinstance(data, (list, tuple)):
            return any(_has_bytes(item) for item in data)
        return _has_bytes(data)

    @classmethod
    def deconstruct_binary(cls, data):
        attachments: list = []
        if isinstance(data, list):
            return [_take_bytes(item, attachments) for item in data], attachments
        return _take_bytes(data, attachments), attachments


def _has_bytes(data) -> bool:
    if isinstance(data, (bytes, bytearray)):
        return True
    return isinstance(data, dict) and any(_has_bytes(value) for value in data.values())


def _take_bytes(data, attachments: list):
    """``data`` with the bytes among the values of its objects appended to ``attachments`` and replaced
    by Socket.IO's placeholders; an object without any is itself, not a copy. One pass."""
    if isinstance(data, (bytes, bytearray)):
        attachments.append(data)
        return {"_placeholder": True, "num": len(attachments) - 1}
    if not isinstance(data, dict):
        return data
    out = None
    for key, value in data.items():
        if isinstance(value, (bytes, bytearray, dict)) and (taken := _take_bytes(value, attachments)) is not value:
            if out is None:
                out = dict(data)
            out[key] = taken
    return data if out is None else out


class OneLine(logging.Filter):
    """Write a record's exception as one line: a malformed packet is the client's fault, not a
    failure of the relay worth a traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            record.msg = f"{record.getMessage()}: {type(exc).__name__}: {str(exc)[:100]}"
            record.args = None
            record.exc_info = None
            record.exc_text = None
            record.levelno, record.levelname = logging.INFO, "INFO"
        return record.levelno >= logging.getLogger(record.name).getEffectiveLevel()


class NoPackets(logging.Filter):
    """Engine.IO and Socket.IO log every packet whole at INFO (a browser's Socket.IO ``auth`` with
    its token, a client's event data): here a packet's log line says its type and size only, and
    an event's name only when it is one the relay takes (a client may name an event anything).
    Those lines, and the other per-message ones, are DEBUG's: at INFO a relay's log is about the
    connections it closes, not every browser's traffic."""

    PACKETS = ("%s: Received packet %s data %s", "%s: Sending packet %s data %s")
    EVENT = 'received event "%s" from %s [%s]'
    EVENTS = frozenset({"subscribe", "connect", "disconnect"})
    CHATTER = frozenset({*PACKETS, EVENT, 'emitting event "%s" to %s [%s]', "%s is entering room %s [%s]",
                         "%s is leaving room %s [%s]", "received ack from %s [%s]"})

    def filter(self, record: logging.LogRecord) -> bool:
        if record.msg in self.CHATTER:
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        if record.msg in self.PACKETS and isinstance(record.args, tuple) and len(record.args) == 3:
            sid, kind, data = record.args
            size = len(data) if isinstance(data, (str, bytes, bytearray)) else len(repr(data))
            record.msg = record.msg.replace("data %s", "(%d bytes)")
            record.args = (sid, kind, size)
        elif record.msg == self.EVENT and isinstance(record.args, tuple) and len(record.args) == 3:
            event, sid, namespace = record.args
            record.args = (event if event in self.EVENTS else "(another)", sid, namespace)
        return True


def _quiet_logger(name: str) -> logging.Logger:
    logger = logging.getLogger(name)
    for kind in (NoPackets, OneLine):
        if not any(isinstance(f, kind) for f in logger.filters):
            logger.addFilter(kind())
    return logger


def create_sio(manager: socketio.AsyncManager | None = None) -> socketio.AsyncServer:
    """The relay's Socket.IO server for browsers (attach it to the aiohttp app); ``manager``: its
    client manager (:mod:`dcuscope.relay.api.fanout`; None: python-socketio's in-process one)."""
    return socketio.AsyncServer(async_mode="aiohttp", serializer=JsonPacket, client_manager=manager,
                                max_http_buffer_size=MAX_UI_MESSAGE_BYTES, cors_allowed_origins=same_origin,
                                logger=_quiet_logger("relay.sio"), engineio_logger=_quiet_logger("relay.eio"),
                                ping_interval=10, ping_timeout=10)


def same_origin(origin: str | None, environ: dict) -> bool:
    """Whether a browser's ``Origin`` is the relay's own page: Engine.IO's default check, but over TLS
    too (its aiohttp driver takes every request for ``http`` unless a proxy said ``X-Forwarded-Proto``,
    so it refused the page of a relay serving HTTPS itself)."""
    host = environ.get("HTTP_HOST")
    if origin is None or host is None:
        return False
    request = environ.get("aiohttp.request")
    scheme = "https" if request is not None and request.secure else environ.get("wsgi.url_scheme", "http")
    allowed = {f"{scheme}://{host}"}
    if "HTTP_X_FORWARDED_PROTO" in environ or "HTTP_X_FORWARDED_HOST" in environ:  # as Engine.IO's default
        forwarded = environ.get("HTTP_X_FORWARDED_PROTO", scheme).split(",")[0].strip()
        allowed.add(f"{forwarded}://{environ.get('HTTP_X_FORWARDED_HOST', host).split(',')[0].strip()}")
    return origin in allowed


@web.middleware
async def sio_errors(request: web.Request, handler) -> web.StreamResponse:
    """End a Socket.IO request whose handler raised on a client's garbage, in one log line."""
    try:
        return await handler(request)
    except web.HTTPException:
        raise
    except Exception as exc:  # noqa: BLE001 - what Engine.IO's unguarded packet decoding raises
        if not request.path.startswith(SIO_PATH):
            raise
        log.info("closing Socket.IO connection: %s: %s", type(exc).__name__, str(exc)[:100])
        raise web.HTTPBadRequest(text="malformed Socket.IO packet") from None
