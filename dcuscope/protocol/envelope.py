"""The envelope of the ingest WebSocket (``GET /ingest``): one message per frame.

Binary frames, node to relay only, each hold one batch (:func:`dcuscope.protocol.wire.encode_batch`):
the batch header already names its run and sequence number, which the acknowledgement echoes.
Text frames hold one JSON object each::

    node -> relay  {"v": 2, "type": "hello" | "sync" | "clock" | "end", "id": 7, "data": {...}}
    relay -> node  {"v": 2, "type": "reply", "id": 7, "data": {...}}      answer to a message with an id
                   {"v": 2, "type": "ack", "seq": 12, "ok": true[, "dup": true]}
                   {"v": 2, "type": "ack", "seq": 12, "ok": false, "error": "...", "retry_ms": 500}
                                                     not stored: hold every batch that long, then send again
                   {"v": 2, "type": "error", "error": "..."}                 then the relay closes

``v`` is :data:`dcuscope.protocol.wire.PROTOCOL_VERSION`; a message of another version, of an unknown
type or of another shape is a protocol error, answered with ``error`` and a closed connection.
``id`` is optional (``clock`` needs no answer), a non-negative integer chosen by the node.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.wire import INT64_MAX, PROTOCOL_VERSION

REQUESTS = frozenset({"hello", "sync", "clock", "end"})
"""Message types a node may send as text."""
REPLIES = frozenset({"reply", "ack", "error"})


@dataclass(frozen=True)
class Message:
    type: str
    data: object
    id: int | None = None


def decode_request(text: str) -> Message:
    """A node's text message; :class:`ProtocolError` for anything else."""
    d = _object(text)
    kind = d.get("type")
    if kind not in REQUESTS:
        raise ProtocolError(f"unknown message type {str(kind)[:40]!r}")
    ident = d.get("id")
    if ident is not None and not (isinstance(ident, int) and not isinstance(ident, bool) and 0 <= ident <= INT64_MAX):
        raise ProtocolError("message id must be a non-negative integer")
    if not d.keys() <= {"v", "type", "id", "data"}:
        raise ProtocolError("message holds unknown fields")
    return Message(kind, d.get("data"), ident)


def decode_reply(text: str) -> dict:
    """A relay's text message, as the node reads it."""
    d = _object(text)
    if d.get("type") not in REPLIES:
        raise ProtocolError(f"unknown message type {str(d.get('type'))[:40]!r}")
    return d


def _object(text: str) -> dict:
    try:
        d = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ProtocolError(f"message is not JSON: {str(exc)[:80]}") from exc
    if not isinstance(d, dict):
        raise ProtocolError("message must be a JSON object")
    if d.get("v") != PROTOCOL_VERSION or isinstance(d.get("v"), bool):
        raise ProtocolError(f"unsupported message version {str(d.get('v'))[:20]} (this relay speaks {PROTOCOL_VERSION})")
    return d


def request(kind: str, data: object = None, ident: int | None = None) -> str:
    d: dict = {"v": PROTOCOL_VERSION, "type": kind, "data": data}
    if ident is not None:
        d["id"] = ident
    return json.dumps(d)


def reply(ident: int, data: object) -> str:
    return json.dumps({"v": PROTOCOL_VERSION, "type": "reply", "id": ident, "data": data})


def ack(seq: int, ok: bool = True, *, dup: bool = False, error: str = "", retry_ms: int = 0) -> str:
    """``retry_ms``: with ``ok: false``, how long the node should hold all its batches (storage failing)."""
    d: dict = {"v": PROTOCOL_VERSION, "type": "ack", "seq": seq, "ok": ok}
    if dup:
        d["dup"] = True
    if error:
        d["error"] = error
    if retry_ms:
        d["retry_ms"] = retry_ms
    return json.dumps(d)


def error(message: str) -> str:
    return json.dumps({"v": PROTOCOL_VERSION, "type": "error", "error": message})
