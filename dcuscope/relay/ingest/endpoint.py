"""The ingest WebSocket ``GET /ingest``: where nodes connect, say hello, ship batches, sync clocks.

A node opens ``ws://HOST:PORT/ingest`` with ``Authorization: Bearer TOKEN`` (or ``?token=``)
when the relay takes credentials: :mod:`dcuscope.relay.guard.policy` refuses one that may not stream with HTTP
401 and its reason before the upgrade (a viewer's included), and binds a node's own to its name (with
``--tls-client-ca``, the name its client certificate gives: 403 without one); a connection beyond the
cap is refused too (503). Then, in the envelope of :mod:`dcuscope.protocol.envelope`:

- ``hello`` {proto, run, header, lost, floor, ptp[, doubt]} -> reply {ok, run, session[, stored, clock_port,
  clock_key, clock_secret]}; ``stored``: which batches of ``doubt`` (sent, then evicted unacknowledged by the node) this
  run's storage holds;
  first, once; ``clock_key`` (hex) lets this connection use the UDP clock exchange on ``clock_port``
  (:mod:`dcuscope.relay.clock.udp`), whose answered (t2, t3) pairs join the connection's sync replies;
  ``clock_secret`` (hex, only on a private connection: :attr:`Ingest.private_channel`) makes that
  exchange tagged, so that nobody who sees its datagrams can answer them;
- a binary batch (:mod:`dcuscope.protocol.wire`) -> ``ack`` {seq, ok[, dup]} once the batch is committed
  (or was stored before), then its events reach the live state; ``ok: false`` if storage failed
  (the node sends it again);
- ``sync`` -> reply {t2, t3}: relay receive and send times (ns, CLOCK_REALTIME);
- ``clock`` {samples, lost, floor, ptp[, via, doubt, forged]}: the node's completed NTP samples and state (with
  ``doubt``, as in hello, a request: the reply says ``stored``). A sample
  counts only if its t2/t3 are a pair this relay sent on this connection or to its UDP key (each once) and its
  offset and round trip are within ``clock_offset_s``/``clock_rtt_s``; others are counted
  (``clock.rejected``) and dropped; ``forged``, the UDP answers the node refused for a wrong tag, is
  shown as ``clock.forged``;
- ``end`` {events, dropped, lost} -> reply {ok}.

``floor``: every batch below it was acknowledged or given up by the node, so the relay stops
waiting for the ones it never got. Anything else (unknown type, wrong version or shape, a
malformed, truncated, oversize or wrong-version batch, a batch before ``hello``, a rate above
the connection's message rate) gets an ``error`` message and the connection closed (1008; 1009
for a message over the size bound); it never touches another run's state. Beyond its
decompressed byte rate (a batch weighs its event count x 24 from its header, before inflating),
or beyond that of all connections together, a connection is not closed: the relay stops reading
from it for a while, so TCP holds the node back.

While storage fails (a full disk), batches are acknowledged ``ok: false`` with ``retry_ms``, how
long the node should hold them; a run's clock and end are kept in memory and written once
storage works again; the connection stays open.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from aiohttp import WSCloseCode, WSMsgType, web

from dcuscope.core.pycompat import ASYNC_TIMEOUTS
from dcuscope.protocol import envelope
from dcuscope.protocol.errors import LimitExceeded, ProtocolError
from dcuscope.protocol.events import EVENT_DTYPE
from dcuscope.protocol.wire import (HEADER_SIZE, MAX_MESSAGE_BYTES, RELAY_HEARTBEAT_S, Batch, check_events, decode_batch,
                                      decode_clock, decode_end, decode_hello, declared_bytes)
from dcuscope.protocol.clockdatagram import new_secret
from dcuscope.model import compiled as compiled_core
from dcuscope.relay.clock.correction import ClockSample, ntp_sample, sample_fault
from dcuscope.relay.clock.udp import ClockUdp
from dcuscope.relay.errors import RelayError
from dcuscope.relay.guard.limits import ByteBucket, Limits, TokenBucket
from dcuscope.relay.guard.policy import PRINCIPAL
from dcuscope.relay.live.state import OWNED_RETRY_MS, RelayState, RunState, TryLater
from dcuscope.relay.store.base import BatchRow, NotOwner, StoreUnavailable

MAX_STORING = 256
"""Batches of one connection being stored at once (a node keeps 64 in flight)."""
CLOSE_TIMEOUT_S = 2.0
SYNCS_KEPT = 256
"""Sync replies (t2, t3) of one connection remembered for its clock report (a node reports
each burst of 4-8 WebSocket or 16 UDP exchanges after it)."""
SAVE_RETRY_S = 1.0
"""Run fields storage failed to write are tried again this often."""
STORAGE_FAILED = "relay storage failing"

log = logging.getLogger(__name__)


@dataclass
class _Conn:
    sid: str
    ws: web.WebSocketResponse
    bucket: TokenBucket
    bytes: ByteBucket
    node: str | None = None
    """The only node name this connection may use (it presented that node's own credential)."""
    run: str | None = None
    syncs: dict[tuple[int, int], None] = field(default_factory=dict)
    """(t2, t3) of the sync replies sent (WebSocket and UDP) and not yet reported, oldest first."""
    clock_key: bytes | None = None
    """This connection's key to the UDP clock exchange (given with the hello reply)."""
    private: bool = False
    """Nobody on the way can read it (TLS): its hello reply may carry a clock secret."""
    closing: bool = False
    hello: bool = False
    """Whether it said hello (taking it may wait on the store: not overdue meanwhile)."""
    tasks: set[asyncio.Task] = field(default_factory=set)
    storing: set[asyncio.Future] = field(default_factory=set)
    """Its batches being stored: each future is done once its store ended."""


class Ingest:
    """The ``/ingest`` handler and the connections it holds."""

    def __init__(self, state: RelayState, limits: Limits = Limits()) -> None:
        self.state = state
        self._limits = limits
        self._conns: dict[str, _Conn] = {}
        self._ids = itertools.count(1)
        self._total = ByteBucket(limits.total_bytes_per_s, limits.total_bytes_per_s)
        self._retry: asyncio.Task | None = None
        self.rejected = 0
        """Connections closed for a bad payload or rate (the fuzz test reads it via /api/health)."""
        self.clock_rejected = 0
        """Clock samples refused, all runs."""
        self.paused = 0
        """Times a connection was held back for its byte rate (or all connections' together)."""
        self.hello_timeouts = 0
        """Connections closed for not saying hello in time (counted in ``rejected`` too)."""
        self.events_in = 0
        self.batches_in = 0
        """Events and batches stored and fed to the live state (``/metrics``)."""
        self.clock_udp: ClockUdp | None = None
        """The UDP clock exchange, once the server listens for it (None: not offered)."""
        compiled = compiled_core.load()
        self._decode = decode_batch if compiled is None else partial(_decode_compiled, compiled)
        """What reads and checks a batch: in one compiled pass where the compiled core loads."""
        self._acks: list[tuple[_Conn, str]] = []
        """Acknowledgements of the rounds settled since the last were sent."""
        self.private_channel: Callable[[web.BaseRequest], bool] = _over_tls
        """Whether a connection cannot be read on the way: the one place that decides which get
        a clock secret (a test without TLS may make it say yes)."""

    @property
    def connected(self) -> int:
        """Ingest WebSocket connections held now."""
        return len(self._conns)

    async def handle(self, request: web.Request) -> web.StreamResponse:
        node = self._authorise(request)
        if len(self._conns) >= self._limits.connections:
            raise web.HTTPServiceUnavailable(text="too many connections")
        ws = web.WebSocketResponse(max_msg_size=MAX_MESSAGE_BYTES, heartbeat=RELAY_HEARTBEAT_S, timeout=CLOSE_TIMEOUT_S)
        if not ws.can_prepare(request):
            raise web.HTTPBadRequest(text="/ingest takes a WebSocket")
        try:
            await ws.prepare(request)
        except ConnectionResetError:
            # The node went away during the handshake (stopped as it started). A plain answer,
            # which aiohttp fails to write quietly, ends the request without a logged traceback.
            raise web.HTTPBadRequest(text="connection closed during the handshake") from None
        lim = self._limits
        conn = _Conn(f"ws{next(self._ids)}", ws, TokenBucket(lim), ByteBucket(lim.bytes_per_s, lim.byte_burst),
                     node, private=self.private_channel(request))
        self._conns[conn.sid] = conn
        # A connection that never says hello would hold one of the few ingest places for ever.
        expiry = asyncio.get_running_loop().call_later(self._limits.hello_timeout_s, self._hello_overdue, conn)
        try:
            await self._serve(conn)
        finally:
            expiry.cancel()
            self._conns.pop(conn.sid, None)
            if conn.clock_key is not None and self.clock_udp is not None:
                self.clock_udp.forget(conn.clock_key)
            if conn.tasks or conn.storing:
                # Batches being stored finish (their acknowledgements have nowhere to go), before
                # the run is let go: on a shared store another relay may take it then.
                await asyncio.gather(*conn.tasks, *conn.storing, return_exceptions=True)
            if conn.run is not None:
                self.state.detach(conn.run, conn.sid)
        return ws

    @staticmethod
    def _authorise(request: web.Request) -> str | None:
        """The node name a connection is bound to (None: any): the policy's middleware let only a
        principal that may stream through, and says which."""
        return request[PRINCIPAL].node

    def _hello_overdue(self, conn: _Conn) -> None:
        if not conn.hello and not conn.closing:
            self.hello_timeouts += 1
            task = asyncio.ensure_future(self._reject(conn, f"no hello within {self._limits.hello_timeout_s:g} s"))
            conn.tasks.add(task)
            task.add_done_callback(conn.tasks.discard)

    async def close_all(self) -> None:
        if self._retry is not None:
            self._retry.cancel()
        for conn in list(self._conns.values()):
            await conn.ws.close(code=WSCloseCode.GOING_AWAY, message=b"relay stopping")

    async def let_go(self) -> None:
        """This relay lost the store connection that renewed its runs' leases and stores their
        batches: their nodes are told to come again, here or to another relay, where they resume."""
        held = list(self.state.runs)
        log.warning("ingest: the store connection was lost; the nodes of %d runs are let go", len(held))
        await self._let_go(held, b"relay lost its store; resume")

    async def let_go_runs(self, runs: set[str]) -> None:
        """Another relay took these runs (this relay was silent longer than their leases, or a write
        of theirs was fenced): nothing more is stored, acknowledged or pushed for them here; their
        nodes are told to go on with another relay."""
        held = [self.state.runs[r] for r in runs if r in self.state.runs]
        if not held:
            return
        log.warning("ingest: another relay took %d runs (%s) while this relay was silent longer than their "
                    "leases; their nodes are let go", len(held), ", ".join(sorted(rs.node for rs in held))[:200])
        await self._let_go([rs.run for rs in held], b"another relay took this run; resume")

    async def _let_go(self, runs: list[str], reason: bytes) -> None:
        """Drop ``runs`` from memory and close their connections (TRY_AGAIN_LATER: the nodes resume)."""
        sids = {self.state.runs[r].sid for r in runs if r in self.state.runs} - {None}
        conns = [c for c in self._conns.values() if c.sid in sids]
        for conn in conns:  # before any await: a batch arriving meanwhile finds its connection closing
            conn.closing = True
            conn.run = None  # its run's state goes now: nothing more of it is read, nor detached at the end
        for run in runs:
            self.state.release(run)
        for conn in conns:
            await conn.ws.close(code=WSCloseCode.TRY_AGAIN_LATER, message=reason)

    async def _serve(self, conn: _Conn) -> None:
        async for msg in conn.ws:
            if conn.closing:
                return
            try:
                if msg.type == WSMsgType.BINARY:
                    self._take(conn)
                    await self._pace(conn, declared_bytes(msg.data))
                    await self._on_batch(conn, msg.data)
                elif msg.type == WSMsgType.TEXT:
                    self._take(conn)
                    await self._pace(conn, len(msg.data))
                    await self._on_message(conn, envelope.decode_request(msg.data))
                elif msg.type == WSMsgType.ERROR:
                    if isinstance(msg.data, (*ASYNC_TIMEOUTS, ConnectionError)):
                        # No pong within the heartbeat (protocol.wire.RELAY_HEARTBEAT_S): the node froze or the
                        # network between is cut. Not its fault: the run is let go, to be resumed.
                        log.info("ingest: %s (run %s) silent: %s", conn.sid, conn.run or "-", msg.data)
                        return
                    # aiohttp already closes with 1009 (too big) or 1002 (not WebSocket).
                    self._count_rejection(conn, f"bad frame: {msg.data}")
                    await self._reject_run(conn, f"bad frame: {msg.data}")
                    return
            except ProtocolError as exc:
                if isinstance(exc, LimitExceeded):
                    self.state.refused[exc.limit] = self.state.refused.get(exc.limit, 0) + 1
                await self._reject(conn, str(exc))
                await self._reject_run(conn, str(exc))
                return
            if conn.run is not None:
                # Heard from: the run holds its node's name (Limits.silent_s).
                run = self.state.runs.get(conn.run)
                if run is not None and run.sid == conn.sid:
                    run.last_seen = time.time()

    def _take(self, conn: _Conn) -> None:
        if not conn.bucket.take():
            raise ProtocolError("rate limit exceeded")

    async def _pace(self, conn: _Conn, nbytes: int) -> None:
        """Hold the connection back while it (or all together) is beyond its byte rate: not
        reading its socket meanwhile is what slows the node, through TCP."""
        wait = max(conn.bytes.charge(nbytes), self._total.charge(nbytes))
        if wait > 0:
            self.paused += 1
            await asyncio.sleep(wait)

    def _count_rejection(self, conn: _Conn, message: str) -> None:
        conn.closing = True
        self.rejected += 1
        log.info("ingest: closing %s (run %s): %s", conn.sid, conn.run or "-", message[:200])

    async def _reject(self, conn: _Conn, message: str) -> None:
        if conn.closing:
            return
        self._count_rejection(conn, message)
        try:
            await conn.ws.send_str(envelope.error(message))
        except (ConnectionError, RuntimeError):  # the peer already left
            pass
        # A close reason holds at most 123 bytes.
        await conn.ws.close(code=WSCloseCode.POLICY_VIOLATION, message=message[:100].encode("ascii", "replace"))

    async def _reject_run(self, conn: _Conn, reason: str) -> None:
        """The run of a connection closed for what it sent is kept apart (relay.live.state.reject)."""
        if conn.run is not None:
            await self.state.reject(conn.run, reason)

    async def _send(self, conn: _Conn, text: str) -> None:
        try:
            await conn.ws.send_str(text)
        except (ConnectionError, RuntimeError):  # closed meanwhile: the node resends what it lacks
            pass

    # --- messages -------------------------------------------------------------------------------

    async def _on_message(self, conn: _Conn, msg: envelope.Message) -> None:
        if msg.type == "sync":
            t2 = time.time_ns()
            if msg.id is not None:
                t3 = time.time_ns()
                conn.syncs[(t2, t3)] = None
                if len(conn.syncs) > SYNCS_KEPT:
                    del conn.syncs[next(iter(conn.syncs))]
                await self._send(conn, envelope.reply(msg.id, {"t2": t2, "t3": t3}))
            return
        if msg.type == "hello":
            answer = await self._on_hello(conn, msg.data)
        elif conn.run is None:
            raise ProtocolError(f"{msg.type} before hello")
        elif msg.type == "clock":
            answer = await self._on_clock(conn, self.state.runs[conn.run], msg.data)
        else:
            answer = await self._on_end(self.state.runs[conn.run], msg.data)
        if msg.id is not None:
            await self._send(conn, envelope.reply(msg.id, answer))
        if msg.type == "hello" and conn.run is None:  # not taken now: the node tries again later
            conn.closing = True
            await conn.ws.close(code=WSCloseCode.TRY_AGAIN_LATER, message=b"try again later")

    async def _on_hello(self, conn: _Conn, data: object) -> dict:
        if conn.run is not None:
            raise ProtocolError("hello twice on one connection")
        conn.hello = True
        hello = decode_hello(data, conn.node, max_stages=self._limits.stages, max_name=self._limits.name_chars)
        try:
            attached = await self.state.attach(hello, conn.sid)
        except TryLater as exc:  # owned by another relay, or the store fails: not the node's fault
            return {"ok": False, "error": str(exc), "retry_ms": exc.retry_ms}
        except StoreUnavailable as exc:
            return {"ok": False, "error": str(exc), "retry_ms": self.state.storage.retry_ms()}
        rs = attached.run
        conn.run = rs.run
        stored = await self._stored_of(rs, hello.doubt)
        rs.seqs.advance(hello.floor)
        old = self._conns.get(attached.previous) if attached.previous is not None else None
        if old is not None:
            # The node reconnected before the relay noticed its old connection died.
            await self._reject(old, "superseded by a newer connection of this run")
        silent = self._conns.get(attached.displaced) if attached.displaced is not None else None
        if silent is not None:
            # The node restarted while its former run's connection stayed open, silent.
            await self._reject(silent, f"superseded by a new run of node {rs.node!r}")
        answer = {"ok": True, "run": rs.run, "session": rs.session}
        if hello.doubt:
            answer["stored"] = stored
        if attached.secret is not None:
            answer["secret"] = attached.secret
        if self.clock_udp is not None:
            # Over plaintext a secret would be seen by whoever sees the datagrams it guards.
            secret = new_secret() if conn.private else None
            conn.clock_key = self.clock_udp.register(conn.syncs, secret)
            answer.update(clock_port=self.clock_udp.port, clock_key=conn.clock_key.hex())
            if secret is not None:
                answer["clock_secret"] = secret.hex()
        return answer

    async def _stored_of(self, rs: RunState, doubt: tuple[int, ...]) -> list[int]:
        """Which of ``doubt`` are stored, once those being stored (sent on the connection that
        died) are. Asked before the floor moves: the node keeps it at its first doubtful batch."""
        stored = []
        for seq in doubt:
            pending = rs.storing.get(seq)
            if pending is not None:
                await asyncio.shield(pending)
            if seq in rs.seqs:
                stored.append(seq)
        return stored

    async def _on_clock(self, conn: _Conn, rs: RunState, data: object) -> dict:
        report = decode_clock(data)
        accepted = [s for s in (self._check_sample(conn, rs, times, report.via) for times in report.samples) if s]
        rs.clock.add_samples(accepted)
        rs.ptp = report.ptp
        rs.spool = report.spool
        rs.lost = max(rs.lost, report.lost)
        rs.clock_forged = max(rs.clock_forged, report.forged)
        stored = await self._stored_of(rs, report.doubt)
        rs.seqs.advance(report.floor)
        clock = dict(self.state.clock_view(rs), ptp=rs.ptp)
        # The whole (bounded) history: storage keeps exactly it, so a write that failed and is
        # retried later (``_update_run``) loses no segment.
        fields = {"history": [s.to_dict() for s in rs.clock.history]} if accepted else {}
        answer = await self._update_run(rs, clock=clock, lost=rs.lost, **fields)
        return dict(answer, stored=stored) if report.doubt else answer

    def _check_sample(self, conn: _Conn, rs: RunState, times: tuple[int, int, int, int],
                      via: str) -> ClockSample | None:
        """The sample if it counts, else None (counted and noted as refused)."""
        t1, t2, t3, t4 = times
        sample = ntp_sample(t1, t2, t3, t4, via)
        if (t2, t3) not in conn.syncs:
            fault = "t2/t3 not from this relay's sync replies on this connection"
        else:
            del conn.syncs[(t2, t3)]  # a pair counts once: no replaying it
            lim = self._limits
            fault = sample_fault(sample, int(lim.clock_offset_s * 1e9), int(lim.clock_rtt_s * 1e9))
        if fault is None:
            return sample
        if not rs.clock_rejected:
            log.warning("ingest: run %s (%s): clock sample rejected: %s", rs.run, rs.node, fault)
        rs.clock_rejected += 1
        rs.clock_fault = fault
        self.clock_rejected += 1
        return None

    async def _on_end(self, rs: RunState, data: object) -> dict:
        written, dropped, lost, ended_ns = decode_end(data)
        rs.ended, rs.written, rs.dropped, rs.lost = True, written, dropped, max(rs.lost, lost)
        rs.live.finish()
        clock = dict(self.state.clock_view(rs), ptp=rs.ptp)
        now = time.time_ns()
        # The node's own end time where it says one (a drained run ended hours ago): never in the future.
        ended = now if not ended_ns or ended_ns > now else ended_ns
        return await self._update_run(rs, ended_ns=ended, written=written, dropped=dropped, lost=rs.lost,
                                      clock=clock)

    async def _update_run(self, rs: RunState, **fields) -> dict:
        """Write run fields; if storage fails, keep them (and any not written before) in memory
        and write them once it works: the node's data is not at fault, its connection stays."""
        rs.unsaved.update(fields)
        fields, rs.unsaved = rs.unsaved, {}
        try:
            await self.state.storage.call("update_run", rs.run, **fields)
        except NotOwner:  # another relay holds the run now: its node tells that one
            return {"ok": False, "error": "another relay holds this run", "retry_ms": OWNED_RETRY_MS}
        except RelayError:  # storage logs that it fails, once
            rs.unsaved = {**fields, **rs.unsaved}  # newer values, set meanwhile, win
            if self._retry is None or self._retry.done():
                self._retry = asyncio.create_task(self._save_later())
            return {"ok": False, "error": STORAGE_FAILED, "retry_ms": self.state.storage.retry_ms()}
        return {"ok": True}

    async def _save_later(self) -> None:
        while any(rs.unsaved for rs in self.state.runs.values()):
            await asyncio.sleep(SAVE_RETRY_S)
            for rs in [rs for rs in self.state.runs.values() if rs.unsaved]:
                if not (await self._update_run(rs))["ok"]:
                    break

    # --- batches --------------------------------------------------------------------------------

    async def _on_batch(self, conn: _Conn, data: bytes) -> None:
        if conn.run is None:
            raise ProtocolError("batch before hello")
        if len(conn.storing) >= MAX_STORING:
            raise ProtocolError(f"more than {MAX_STORING} batches unacknowledged")
        rs = self.state.runs[conn.run]
        batch = self._decode(data, len(rs.header.stages))
        if batch.run != rs.run:
            raise ProtocolError("batch of another run on this connection")
        named = rs.live.admit_sources(batch.events["source"], self._limits.sources)
        if named > self._limits.sources:
            raise LimitExceeded("sources", f"run {rs.run} would name {named} distinct source ids, more than this "
                                           f"relay takes ({self._limits.sources}: --limit sources=N)")
        rs.last_seen = time.time()
        seq = batch.seq
        if seq in rs.seqs:
            rs.duplicates += 1
            await self._send(conn, envelope.ack(seq, dup=True))
        elif seq in rs.storing:
            # The same batch, resent on a newer connection while the first copy is being stored.
            self._await_copy(conn, rs, seq)
        else:
            self._commit(conn, rs, batch)

    def _await_copy(self, conn: _Conn, rs: RunState, seq: int) -> None:
        """Acknowledge ``seq`` on ``conn`` once its first copy's store ended (rare: a task of its own)."""
        async def answer(pending: asyncio.Future) -> None:
            if await asyncio.shield(pending):
                rs.duplicates += 1
                await self._send(conn, envelope.ack(seq, dup=True))
            else:
                await self._send(conn, self._refused(seq))
        done = asyncio.get_running_loop().create_future()
        conn.storing.add(done)
        task = asyncio.create_task(answer(rs.storing[seq]))
        task.add_done_callback(lambda t: (conn.storing.discard(done), done.set_result(None)))
        task.add_done_callback(_report_failure)

    def _commit(self, conn: _Conn, rs: RunState, batch: Batch) -> None:
        """Queue ``batch`` with the store; once its round committed, :meth:`_stored` feeds the live state
        and acknowledges it. A batch reaches the statistics once it is stored, so a batch storage
        refused, sent again, counts once."""
        done = asyncio.get_running_loop().create_future()
        rs.storing[batch.seq] = done
        conn.storing.add(done)
        row = BatchRow(rs.run, batch.seq, len(batch.events), batch.compressed, batch.payload)
        try:
            self.state.storage.queue_batch(row, partial(self._stored, conn, rs, batch, done))
        except RelayError as exc:
            self._stored(conn, rs, batch, done, None, exc)

    def _stored(self, conn: _Conn, rs: RunState, batch: Batch, done: asyncio.Future, new: bool | None,
                error: BaseException | None) -> None:
        """How ``batch``'s store ended (on the event loop, with its round): fed to the live state if new,
        and its acknowledgement queued; none when the store refused it for another relay owns the run
        now (its node is let go, :meth:`let_go_runs`, and told nothing)."""
        rs.storing.pop(batch.seq, None)
        conn.storing.discard(done)
        done.set_result(error is None)
        if isinstance(error, NotOwner):
            return
        if error is not None:
            if not isinstance(error, RelayError):  # a bug, not the store failing: said loudly
                log.error("ingest: storing a batch failed", exc_info=error)
            self._acknowledge(conn, self._refused(batch.seq))  # storage logs that it fails, once
            return
        rs.seqs.add(batch.seq)
        if new:
            rs.live.add(batch.events, admitted=True)  # its sources were, as it arrived
            self.state.journeys.add(rs.run, batch.events)
            self.state.note_events(rs)
            self.events_in += len(batch.events)
            self.batches_in += 1
        else:  # stored before this relay's run state knew it: already in the live state
            rs.duplicates += 1
        self._acknowledge(conn, envelope.ack(batch.seq, dup=not new))

    def _acknowledge(self, conn: _Conn, text: str) -> None:
        """Queue an acknowledgement: a round's leave together, from one task (not one per batch)."""
        if not self._acks:
            task = asyncio.get_running_loop().create_task(self._send_acks())
            task.add_done_callback(_report_failure)
        self._acks.append((conn, text))

    async def _send_acks(self) -> None:
        acks, self._acks = self._acks, []
        for conn, text in acks:
            await self._send(conn, text)

    def _refused(self, seq: int) -> str:
        return envelope.ack(seq, False, error=STORAGE_FAILED, retry_ms=self.state.storage.retry_ms())


def _report_failure(task: asyncio.Task) -> None:
    # A bug, not a node's fault: said loudly, since nobody awaits these tasks' results.
    if not task.cancelled() and task.exception() is not None:
        log.error("ingest: acknowledging batches failed", exc_info=task.exception())


def _decode_compiled(core: compiled_core.CompiledCore, data: object, n_stages: int) -> Batch:
    """:func:`decode_batch` with the header read and the events checked in one compiled pass;
    :func:`decode_batch` says what is wrong with a batch this refuses."""
    if isinstance(data, (bytearray, memoryview)):
        data = bytes(data)
    if isinstance(data, bytes):
        code, seq, _ = core.decode_header(data, n_stages)
        if code == compiled_core.BATCH_OK:
            payload = data[HEADER_SIZE:]
            return Batch(data[8:24].hex(), seq, np.frombuffer(payload, EVENT_DTYPE), payload, False)
        if code == compiled_core.BATCH_INFLATE:
            return decode_batch(data, n_stages, check=partial(_check_compiled, core))
    decode_batch(data, n_stages)  # raises, saying why
    raise ProtocolError("batch refused")  # were the two to disagree


def _check_compiled(core: compiled_core.CompiledCore, events: np.ndarray, n_stages: int) -> None:
    """:func:`check_events` in one compiled pass; numpy's says what is wrong with a batch it refuses."""
    if core.first_invalid(events, n_stages) >= 0:
        check_events(events, n_stages)
        raise ProtocolError("an event is invalid")  # were the two to disagree


def _over_tls(request: web.BaseRequest) -> bool:
    return request.secure
