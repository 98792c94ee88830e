"""Socket.IO namespace ``/ingest``: where nodes connect, say hello, ship batches, sync clocks.

Messages (see :mod:`relay.protocol`), each answered through the Socket.IO acknowledgement:

- connect with ``auth={"token": T, "node": NAME}``; refused without the token;
- ``hello`` {proto, run, header, lost, ptp} -> {ok, run, session};
- ``batch`` <binary> -> {ok, seq[, dup]} once the batch is committed (or was stored before);
- ``sync`` -> {t2, t3}: relay receive and send times (ns, CLOCK_REALTIME);
- ``clock`` {samples, lost, ptp}: the node's completed NTP samples and state;
- ``end`` {events, dropped, lost} -> {ok}.

Anything else (unknown event, wrong arguments, a malformed, truncated, oversize or
wrong-version payload, a batch before ``hello``, a rate above the connection's bounds) gets a
``relay_error`` message and the connection closed; it never touches another run's state.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import socketio
from socketio.exceptions import ConnectionRefusedError as Refused

from relay import storage as db
from relay.auth import socket_token, token_matches
from relay.errors import ProtocolError, RelayError
from relay.limits import Limits, TokenBucket
from relay.protocol import MAX_NAME, decode_batch, decode_clock, decode_end, decode_hello
from relay.state import RelayState

NAMESPACE = "/ingest"
EVENTS = frozenset({"connect", "disconnect", "hello", "batch", "sync", "clock", "end"})
DEFAULT_MAX_CONNECTIONS = 1024

log = logging.getLogger(__name__)


@dataclass
class _Conn:
    node: str
    bucket: TokenBucket
    run: str | None = None
    closing: bool = False


class IngestNamespace(socketio.AsyncNamespace):
    def __init__(self, state: RelayState, token: str | None, limits: Limits = Limits(),
                 max_connections: int = DEFAULT_MAX_CONNECTIONS) -> None:
        super().__init__(NAMESPACE)
        self.state = state
        self._token = token
        self._limits = limits
        self._max_connections = max_connections
        self._conns: dict[str, _Conn] = {}
        self.rejected = 0
        """Connections closed for a bad payload or rate (the fuzz test reads it via /api/health)."""

    async def trigger_event(self, event: str, *args):
        if event in ("connect", "disconnect"):
            try:
                return await super().trigger_event(event, *args)
            except Refused:
                raise
            except Exception as exc:  # noqa: BLE001 - a malformed connect is refused, not a crash
                if event == "connect":
                    raise Refused("malformed connect") from exc
                log.exception("ingest: disconnect handler failed")
                return None
        if event not in EVENTS:
            sid = args[0] if args and isinstance(args[0], str) else None
            if sid is not None:
                return await self._reject(sid, f"unknown event {event!r}"[:200])
            return None
        if len(args) > 2:
            # Every message carries at most one argument: more is a malformed message.
            return await self._reject(args[0], f"malformed {event!r} message")
        try:
            return await super().trigger_event(event, *args)
        except ProtocolError as exc:
            return await self._reject(args[0], str(exc))
        except Exception as exc:  # noqa: BLE001 - one bad connection must not take the relay down
            log.exception("ingest: %s from %s failed", event, args[0] if args else "?")
            return await self._reject(args[0], f"{event} failed: {exc}"[:200])

    async def _reject(self, sid: str, message: str) -> dict:
        conn = self._conns.get(sid)
        if conn is not None and conn.closing:
            return {"ok": False, "error": message}
        if conn is not None:
            conn.closing = True
        self.rejected += 1
        log.info("ingest: closing %s (%s): %s", sid, conn.node if conn else "?", message)
        try:
            await self.emit("relay_error", {"error": message}, to=sid)
            eio_sid = self.server.manager.eio_sid_from_sid(sid, NAMESPACE)
            await self.disconnect(sid)
            if eio_sid is not None:
                await self.server.hang_up(eio_sid)
        except Exception:  # noqa: BLE001 - the peer may already be gone
            pass
        return {"ok": False, "error": message}

    def _conn(self, sid: str, nbytes: int) -> _Conn:
        conn = self._conns.get(sid)
        if conn is None or conn.closing:
            raise ProtocolError("not connected")
        if not conn.bucket.take(nbytes):
            raise ProtocolError("rate limit exceeded")
        return conn

    # --- handlers -----------------------------------------------------------------------------

    async def on_connect(self, sid: str, environ: dict, auth: object = None) -> None:
        if not token_matches(self._token, socket_token(auth, environ)):
            raise Refused("unauthorized: wrong or missing token")
        node = auth.get("node") if isinstance(auth, dict) else None
        if not (isinstance(node, str) and 0 < len(node) <= MAX_NAME and node.isprintable()):
            raise Refused("a node must name itself: auth={'node': NAME}")
        if len(self._conns) >= self._max_connections:
            raise Refused("too many connections")
        self._conns[sid] = _Conn(node, TokenBucket(self._limits))

    async def on_disconnect(self, sid: str, reason: object = None) -> None:
        conn = self._conns.pop(sid, None)
        if conn is not None and conn.run is not None:
            self.state.detach(conn.run, sid)

    async def on_hello(self, sid: str, data: object = None) -> dict:
        conn = self._conn(sid, 0)
        if conn.run is not None:
            raise ProtocolError("hello twice on one connection")
        hello = decode_hello(data, conn.node)
        rs, previous = await self.state.attach(hello, sid)
        conn.run = rs.run
        if previous is not None and previous in self._conns:
            # The node reconnected before the relay noticed its old connection died.
            await self._reject(previous, "superseded by a newer connection of this run")
        return {"ok": True, "run": rs.run, "session": rs.session}

    async def on_batch(self, sid: str, data: object = None) -> dict:
        size = len(data) if isinstance(data, (bytes, bytearray)) else 0
        conn = self._conn(sid, size)
        if conn.run is None:
            raise ProtocolError("batch before hello")
        rs = self.state.runs[conn.run]
        batch = decode_batch(data, len(rs.header.stages))
        if batch.run != rs.run:
            raise ProtocolError("batch of another run on this connection")
        rs.last_seen = time.time()
        if batch.seq in rs.seqs:
            rs.duplicates += 1
            return {"ok": True, "seq": batch.seq, "dup": True}
        rs.seqs.add(batch.seq)
        rs.live.add(batch.events)
        try:
            await self.state.storage.put_batch(rs.run, batch.seq, len(batch.events), batch.compressed, batch.payload)
        except RelayError as exc:
            rs.seqs.discard(batch.seq)
            log.error("%s", exc)
            return {"ok": False, "error": "relay storage failed"}
        return {"ok": True, "seq": batch.seq}

    async def on_sync(self, sid: str, data: object = None) -> dict:
        t2 = time.time_ns()
        self._conn(sid, 0)
        return {"t2": t2, "t3": time.time_ns()}

    async def on_clock(self, sid: str, data: object = None) -> dict:
        conn = self._conn(sid, 0)
        if conn.run is None:
            raise ProtocolError("clock before hello")
        report = decode_clock(data)
        rs = self.state.runs[conn.run]
        for sample in report.samples:
            rs.clock.add(*sample)
        rs.ptp = report.ptp
        rs.lost = max(rs.lost, report.lost)
        clock = dict(self.state.clock_view(rs), ptp=rs.ptp)
        await self.state.storage.call(db.update_run, rs.run, clock=clock, lost=rs.lost)
        return {"ok": True}

    async def on_end(self, sid: str, data: object = None) -> dict:
        conn = self._conn(sid, 0)
        if conn.run is None:
            raise ProtocolError("end before hello")
        written, dropped, lost = decode_end(data)
        rs = self.state.runs[conn.run]
        rs.ended, rs.written, rs.dropped, rs.lost = True, written, dropped, max(rs.lost, lost)
        clock = dict(self.state.clock_view(rs), ptp=rs.ptp)
        await self.state.storage.call(db.update_run, rs.run, ended_ns=time.time_ns(), written=written,
                                      dropped=dropped, lost=rs.lost, clock=clock)
        return {"ok": True}
