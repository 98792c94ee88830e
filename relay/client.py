"""Node side of the transport: :class:`RelayExporter` ships probe events to a relay.

It implements the ``probes.events.Exporter`` protocol. ``write`` only copies the events into a
pending list under a short lock and returns: it never waits for the network. A thread of its
own runs an asyncio loop with a python-socketio ``AsyncClient`` that cuts the pending events
into numbered batches (:mod:`relay.protocol`), keeps every batch until the relay acknowledges
it (the relay acknowledges after its database committed the batch), resends what is not
acknowledged after a reconnect, and reconnects with exponential backoff. The buffer of
unacknowledged events is bounded (``max_buffer_events``); beyond it the oldest batches are
dropped and counted as ``lost``, a count the relay receives with the next ``hello``/``clock``
message and with ``end``.

On each connection it also measures the clock offset to the relay (NTP-style exchanges,
``sync``) and reports them with the node's linuxptp state (``clock``); the relay estimates.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import random
import threading
import time
import uuid
from collections import OrderedDict, deque

import numpy as np
import socketio

from probes.events import CLOCKS, EVENT_DTYPE, TraceHeader
from relay.clock import read_ptp_state
from relay.errors import RelayError
from relay.protocol import MAX_BATCH_EVENTS, PROTOCOL_VERSION, encode_batch

NAMESPACE = "/ingest"
DEFAULT_BATCH_EVENTS = 8192
DEFAULT_FLUSH_INTERVAL_S = 0.05
DEFAULT_MAX_BUFFER_EVENTS = 2_000_000
"""About 46 MiB, 7.7 minutes of a paper-sized DCU (4,300 events/s)."""
DEFAULT_WINDOW = 64
"""Batches in flight (sent, not acknowledged) on one connection."""
SYNC_BURST_FIRST, SYNC_BURST = 8, 4
ACK_TIMEOUT_S = 30.0

log = logging.getLogger(__name__)


class RelayExporter:
    """Ships events to ``url`` (``http://HOST:PORT``) as node ``node``.

    ``clock`` names the clock the probes read (``probes.events.CLOCKS``): the NTP exchanges
    must read the same one. ``clock_offset_ns`` is a testing aid: it shifts every clock reading
    of this client, as the probes shift event timestamps, to inject a known skew.
    """

    def __init__(self, url: str, node: str, token: str | None = None, clock: str = "realtime",
                 clock_offset_ns: int = 0, *, compress: bool = False,
                 batch_events: int = DEFAULT_BATCH_EVENTS, flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
                 max_buffer_events: int = DEFAULT_MAX_BUFFER_EVENTS, window: int = DEFAULT_WINDOW,
                 sync_interval_s: float = 2.0, ptp_interval_s: float = 10.0, close_timeout_s: float = 5.0,
                 backoff_s: tuple[float, float] = (0.1, 5.0)) -> None:
        if clock not in CLOCKS:
            raise RelayError(f"relay exporter: unknown clock {clock!r} (one of {', '.join(CLOCKS)})")
        if not url.startswith(("http://", "https://")):
            raise RelayError(f"relay URL must start with http:// or https://, not {url!r}")
        if not node:
            raise RelayError("relay exporter: the node needs a name")
        self.url, self.node, self._token = url.rstrip("/"), node, token
        self._clock_id, self._offset = CLOCKS[clock], int(clock_offset_ns)
        self._compress = compress
        self._batch_events = max(1, min(int(batch_events), MAX_BATCH_EVENTS))
        self._flush_interval = flush_interval_s
        self._max_events = int(max_buffer_events)
        self._window = max(1, int(window))
        self._sync_interval, self._ptp_interval = sync_interval_s, ptp_interval_s
        self._close_timeout, self._backoff = close_timeout_s, backoff_s
        self.run_id = uuid.uuid4().hex
        self._header: dict | None = None

        # Shared with the caller's thread: only these, under the lock.
        self._lock = threading.Lock()
        self._pending: list[np.ndarray] = []
        self._pending_n = 0
        self._shed = 0  # events refused by write because even the pending list was full

        # Owned by the loop thread.
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._unacked: OrderedDict[int, tuple[bytes, int]] = OrderedDict()
        self._unacked_n = 0
        self._inflight: dict[int, float] = {}
        self._to_send: deque[int] = deque()
        self._next_seq = 0
        self._evicted = 0
        self._written = self._acked = self._sent = self._connects = 0
        self._connected = False
        self._last_error = ""
        self._ptp: dict = {"state": "unavailable", "reason": "not read yet"}
        self._sio: socketio.AsyncClient | None = None

    # --- Exporter protocol (the probe shipping thread) -----------------------------------

    def start(self, header: TraceHeader) -> None:
        if self._thread is not None:
            raise RelayError("relay exporter already started")
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
            # A copy: the shipper may reuse its array after write returns.
            self._pending.append(events.copy())
            self._pending_n += n
            self._written += n
            wake = self._pending_n >= self._batch_events
        if wake and self._loop is not None:
            self._loop.call_soon_threadsafe(self._wake.set)

    def close(self, dropped: int) -> None:
        """Send what is buffered (up to ``close_timeout_s``), tell the relay the run ended."""
        if self._thread is None or self._loop is None:
            return
        future = asyncio.run_coroutine_threadsafe(self._finish(int(dropped)), self._loop)
        try:
            future.result(self._close_timeout + 5)
        except Exception as exc:  # noqa: BLE001 - closing must not raise into the pipeline's teardown
            log.warning("relay exporter %s: close: %s", self.node, exc)
        self._thread.join(5)

    # --- introspection ------------------------------------------------------------------------

    @property
    def lost(self) -> int:
        """Events this node will never deliver (buffer overflow)."""
        return self._evicted + self._shed

    def counters(self) -> dict:
        return {
            "run": self.run_id, "connected": self._connected, "connects": self._connects,
            "written": self._written, "sent": self._sent, "acked": self._acked, "lost": self.lost,
            "buffered": self._unacked_n + self._pending_n, "last_error": self._last_error,
        }

    # --- loop thread --------------------------------------------------------------------------

    def _thread_main(self, ready: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._wake = asyncio.Event()
        self._progress = asyncio.Event()
        self._stop = asyncio.Event()
        self._loop = loop  # last: write() uses it as the sign that _wake exists
        ready.set()
        try:
            loop.run_until_complete(self._main())
        except Exception:  # noqa: BLE001 - a dying shipper must say why, not kill the process
            log.exception("relay exporter %s stopped", self.node)
        finally:
            loop.close()

    def _now(self) -> int:
        return time.clock_gettime_ns(self._clock_id) + self._offset

    async def _main(self) -> None:
        tasks = [asyncio.create_task(self._flush_loop()), asyncio.create_task(self._ptp_loop())]
        try:
            await self._connection_loop()
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _flush_loop(self) -> None:
        while True:
            await _wait(self._wake, self._flush_interval)
            self._wake.clear()
            self._cut_batches()

    def _cut_batches(self) -> None:
        with self._lock:
            pending, self._pending, self._pending_n = self._pending, [], 0
        if not pending:
            return
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
            self._evicted += n
        self._progress.set()

    async def _ptp_loop(self) -> None:
        while True:
            self._ptp = await read_ptp_state()
            await asyncio.sleep(self._ptp_interval)

    def _hello(self) -> dict:
        return {"proto": PROTOCOL_VERSION, "run": self.run_id, "header": self._header,
                "lost": self.lost, "ptp": self._ptp}

    async def _connection_loop(self) -> None:
        delay = self._backoff[0]
        while not self._stop.is_set():
            sio = socketio.AsyncClient(reconnection=False, logger=False, engineio_logger=False)
            gone = asyncio.Event()
            sio.on("disconnect", lambda *_: gone.set(), namespace=NAMESPACE)
            sio.on("relay_error", self._on_relay_error, namespace=NAMESPACE)
            refusal: list = []
            sio.on("connect_error", lambda data=None: refusal.append(data), namespace=NAMESPACE)
            try:
                await sio.connect(self.url, auth={"token": self._token, "node": self.node},
                                  namespaces=[NAMESPACE], transports=["websocket"], wait_timeout=5)
                reply = await sio.call("hello", self._hello(), namespace=NAMESPACE, timeout=10)
                if not (isinstance(reply, dict) and reply.get("ok")):
                    raise RelayError(f"relay refused hello: {reply!r}")
            except (socketio.exceptions.SocketIOError, OSError, asyncio.TimeoutError, RelayError) as exc:
                why = f" ({_reason(refusal[-1])})" if refusal else ""
                self._note_error(f"cannot reach relay {self.url}: {exc}{why}")
                await _quietly_disconnect(sio)
                try:
                    await asyncio.wait_for(self._stop.wait(), delay * random.uniform(0.8, 1.2))
                except asyncio.TimeoutError:
                    pass
                delay = min(delay * 2, self._backoff[1])
                continue
            delay = self._backoff[0]
            self._connects += 1
            self._connected, self._sio = True, sio
            self._inflight.clear()
            self._to_send = deque(self._unacked.keys())
            workers = [asyncio.create_task(self._sender(sio)), asyncio.create_task(self._syncer(sio))]
            stop = asyncio.create_task(self._stop.wait())
            lost = asyncio.create_task(gone.wait())
            await asyncio.wait([stop, lost, *workers], return_when=asyncio.FIRST_COMPLETED)
            for t in (stop, lost, *workers):
                t.cancel()
            for t in workers:
                if t.done() and not t.cancelled() and t.exception() is not None:
                    self._note_error(f"connection to {self.url} failed: {t.exception()}")
            self._connected, self._sio = False, None
            await _quietly_disconnect(sio)

    async def _sender(self, sio: socketio.AsyncClient) -> None:
        while True:
            while self._to_send and len(self._inflight) < self._window:
                seq = self._to_send.popleft()
                item = self._unacked.get(seq)
                if item is None or seq in self._inflight:
                    continue
                self._inflight[seq] = time.monotonic()
                await sio.emit("batch", item[0], namespace=NAMESPACE, callback=functools.partial(self._on_ack, seq))
                self._sent += item[1]
            self._progress.clear()
            if not await _wait(self._progress, 1.0):
                oldest = min(self._inflight.values(), default=time.monotonic())
                if time.monotonic() - oldest > ACK_TIMEOUT_S:
                    raise RelayError(f"no acknowledgement for {ACK_TIMEOUT_S:.0f} s") from None

    def _on_ack(self, seq: int, reply: object = None) -> None:
        if not (isinstance(reply, dict) and reply.get("ok")):
            self._note_error(f"relay rejected batch {seq}: {reply!r}")
            return
        self._inflight.pop(seq, None)
        item = self._unacked.pop(seq, None)
        if item is not None:
            self._unacked_n -= item[1]
            self._acked += item[1]
        self._progress.set()

    async def _syncer(self, sio: socketio.AsyncClient) -> None:
        burst = SYNC_BURST_FIRST
        while True:
            samples = []
            for _ in range(burst):
                t1 = self._now()
                reply = await sio.call("sync", None, namespace=NAMESPACE, timeout=5)
                t4 = self._now()
                if isinstance(reply, dict) and isinstance(reply.get("t2"), int) and isinstance(reply.get("t3"), int):
                    samples.append([t1, reply["t2"], reply["t3"], t4])
            await sio.emit("clock", {"samples": samples, "lost": self.lost, "ptp": self._ptp}, namespace=NAMESPACE)
            burst = SYNC_BURST
            await asyncio.sleep(self._sync_interval)

    def _on_relay_error(self, data: object = None) -> None:
        self._note_error(f"relay error: {data!r}")

    def _note_error(self, message: str) -> None:
        if message != self._last_error:
            log.warning("relay exporter %s: %s", self.node, message)
        self._last_error = message

    async def _finish(self, dropped: int) -> None:
        self._cut_batches()
        deadline = time.monotonic() + self._close_timeout
        while self._unacked and time.monotonic() < deadline:
            self._progress.clear()
            await _wait(self._progress, min(0.2, max(deadline - time.monotonic(), 0.01)))
        if self._unacked:
            log.warning("relay exporter %s: %d events not acknowledged at close", self.node, self._unacked_n)
        sio = self._sio
        if sio is not None and self._connected:
            end = {"events": self._written, "dropped": dropped, "lost": self.lost + self._unacked_n}
            try:
                await sio.call("end", end, namespace=NAMESPACE, timeout=5)
            except (socketio.exceptions.SocketIOError, asyncio.TimeoutError) as exc:
                self._note_error(f"could not send end: {exc}")
        self._stop.set()


async def _wait(event: asyncio.Event, timeout_s: float) -> bool:
    """Wait for ``event`` at most ``timeout_s``; True if it was set. (``asyncio.timeout``
    costs no extra task per wait, unlike ``wait_for``: this runs 20 times a second.)"""
    try:
        async with asyncio.timeout(timeout_s):
            await event.wait()
        return True
    except TimeoutError:
        return False


async def _quietly_disconnect(sio: socketio.AsyncClient) -> None:
    try:
        await sio.disconnect()
    except Exception:  # noqa: BLE001 - tearing down a half-open connection
        pass


def _reason(data: object) -> str:
    if isinstance(data, dict) and "message" in data:
        return str(data["message"])
    return str(data)
