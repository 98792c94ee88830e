"""The relay's store, written by one thread: coroutines queue their writes and wait for the commit.

Batches queued together are committed in one transaction (at most GROUP_LIMIT): a batch is
acknowledged to its node only after the transaction holding it committed. Other operations
(:meth:`Storage.call`: a method of :class:`relay.store.base.Database`) run in the same thread,
in the order they were queued.

While the store fails (a full disk, PostgreSQL down or restarting) every write is refused with
:class:`relay.errors.RelayError`: nodes hold their batches for :meth:`Storage.retry_ms` and send
them again. One line is logged when writes start failing and one when they work again. A lost
connection to a shared store is opened again at the next write; since the runs this relay owned
were owned by the lost connection, it tells the relay (``on_owners_lost``), which lets their
nodes go: they come back, to this relay or another, and resume.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from relay.errors import RelayError
from relay.store.base import BatchRow, Database, NotOwner, StoreUnavailable
from relay.store.engines import open_database

GROUP_LIMIT = 2000
"""Batches committed in one transaction at most."""
RETRY_MS = (250, 5000)
"""What nodes are told to hold their batches for while storage fails: from the first, growing
with how long it has failed (half of it), to the second."""
DESCRIBE_S = 2.0
"""The store's description (the relays sharing it) is refreshed this often."""
WRITES = frozenset({"register_run", "update_run", "mark_rejected", "own_run", "disown_run"})
"""Calls whose success shows that storage works again."""

log = logging.getLogger(__name__)


@dataclass
class _Batch:
    row: BatchRow
    future: asyncio.Future


@dataclass
class _Call:
    name: str | Callable[..., Any]
    args: tuple
    kwargs: dict
    future: asyncio.Future


class Storage:
    """The relay's database, written by one thread; coroutines wait for their commit."""

    def __init__(self, db: str | Path, name: str = "") -> None:
        self.db = db
        """What ``--db`` named: readers (stored sessions) open their own connections to it."""
        self.name = name
        self._database: Database | None = open_database(db, name=name)
        self.location = self._database.location
        self.shared = self._database.shared
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._worker, name="dcuscope-relay-db", daemon=True)
        self.commits = 0
        self.batches_written = 0
        self.reconnects = 0
        self.on_owners_lost: Callable[[], None] | None = None
        """Called on the event loop when the connection that owned this relay's runs was lost."""
        self._described: dict = self._database.describe()
        self._failure: dict | None = None
        """While writes fail: {error, since (epoch s), failed_writes, failed}; None when they work."""

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._thread.start()

    def stop(self) -> None:
        self._queue.put(None)
        self._thread.join(10)
        if self._database is not None and not self._thread.is_alive():
            self._database.close()

    async def put_batch(self, run: str, seq: int, count: int, compressed: bool, payload: bytes) -> bool:
        """Store a batch; True once committed, False if (run, seq) was already stored.
        Raises :class:`RelayError` if it could not be stored."""
        future = self._future()
        self._queue.put(_Batch(BatchRow(run, seq, count, compressed, payload), future))
        return await future

    async def call(self, name: str | Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``Database.<name>(*args, **kwargs)`` in the database thread, or ``name(database, *args,
        **kwargs)`` if it is a function."""
        future = self._future()
        self._queue.put(_Call(name, args, kwargs, future))
        return await future

    @property
    def queued(self) -> int:
        """Writes and calls waiting for the database thread."""
        return self._queue.qsize()

    def health(self) -> dict:
        """{ok, engine, location[, relays]} or, while writes fail, also {error, since,
        failed_writes, failed {what: count}} (for /api/health)."""
        failure = self._failure
        out = dict(self._described, reconnects=self.reconnects)
        if failure is None:
            return dict(out, ok=True)
        return {**out, **failure, "ok": False, "failed": dict(failure["failed"])}

    def retry_ms(self) -> int:
        """How long a node should hold its batches now (storage failing)."""
        failure = self._failure
        failing_s = time.time() - failure["since"] if failure is not None else 0.0
        return int(min(RETRY_MS[1], max(RETRY_MS[0], failing_s * 500)))

    # --- the thread ---------------------------------------------------------------------------

    def _connection(self) -> Database:
        """The open connection, or a new one after the last was lost (StoreUnavailable if not)."""
        if self._database is None:
            self._database = open_database(self.db, name=self.name)
            self.reconnects += 1
            if self.shared and self.on_owners_lost is not None:
                self._soon(self.on_owners_lost)
            log.info("%s: connected again", self.location)
        return self._database

    def _lost(self) -> None:
        """The connection failed: a shared store's is dropped (its runs' ownership with it) and
        opened again at the next write; a file's stays (a full disk is not a lost file)."""
        if self.shared and self._database is not None:
            try:
                self._database.close()
            except Exception:  # noqa: BLE001 - it is being dropped for failing already
                pass
            self._database = None

    def _failed(self, what: str, exc: BaseException) -> RelayError:
        # Logged once when writes start failing and once when they work again, not per write
        # (a full disk fails every write, many a second).
        text = f"{type(exc).__name__}: {exc}" if not isinstance(exc, StoreUnavailable) else str(exc)
        text = text.removeprefix(f"{self.location}: ")
        failure = self._failure
        if failure is None:
            failure = self._failure = {"error": text, "since": time.time(), "failed_writes": 0, "failed": {}}
            log.error("%s: storage failing (%s); batches are held by their nodes until it works again",
                      self.location, text)
        failure["failed_writes"] += 1
        failure["failed"][what] = failure["failed"].get(what, 0) + 1
        failure["error"] = text
        return StoreUnavailable(f"{self.location}: cannot {what}: {text}")

    def _worked(self) -> None:
        failure, self._failure = self._failure, None
        if failure is not None:
            log.warning("%s: storage works again after %d failed writes in %.1f s (%s)", self.location,
                        failure["failed_writes"], time.time() - failure["since"], failure["error"])

    def _future(self) -> asyncio.Future:
        # A queue nobody reads would leave the caller waiting for ever.
        if not self._thread.is_alive():
            raise RelayError(f"{self.location}: storage is not running")
        return asyncio.get_running_loop().create_future()

    def _soon(self, fn: Callable[[], None]) -> None:
        try:
            self._loop.call_soon_threadsafe(fn)
        except RuntimeError:  # the loop closed
            pass

    def _resolve_all(self, outcomes: list[tuple[asyncio.Future, Any, BaseException | None]]) -> None:
        # One wake-up of the event loop per commit, not one per batch.
        def settle() -> None:
            for future, value, error in outcomes:
                if future.done():
                    continue
                if error is not None:
                    future.set_exception(error)
                else:
                    future.set_result(value)
        self._soon(settle)

    def _worker(self) -> None:
        described = time.monotonic()
        while True:
            if time.monotonic() - described >= DESCRIBE_S:
                self._describe()
                described = time.monotonic()
            try:
                item = self._queue.get(timeout=DESCRIBE_S)
            except queue.Empty:
                continue
            if item is None:
                return
            group = [item]
            while len(group) < GROUP_LIMIT:
                try:
                    nxt = self._queue.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    self._queue.put(None)
                    break
                group.append(nxt)
            self._write_batches([g for g in group if isinstance(g, _Batch)])
            for call in (g for g in group if isinstance(g, _Call)):
                self._run_call(call)

    def _describe(self) -> None:
        """What /api/health shows of the store (the relays sharing it come and go)."""
        if self._database is None:
            return
        try:
            self._described = self._database.describe()
        except StoreUnavailable:
            self._lost()

    def _run_call(self, call: _Call) -> None:
        try:
            database = self._connection()
            fn = getattr(database, call.name) if isinstance(call.name, str) else partial(call.name, database)
            value = fn(*call.args, **call.kwargs)
        except StoreUnavailable as exc:  # the store failed (a full disk, a lost server), not the caller
            self._lost()
            what = call.name if isinstance(call.name, str) else getattr(call.name, "__name__", "write")
            outcome = (call.future, None, self._failed(what, exc))
        except Exception as exc:  # noqa: BLE001 - handed to the awaiting coroutine
            outcome = (call.future, None, exc)
        else:
            if call.name in WRITES:
                self._worked()
            outcome = (call.future, value, None)
        self._resolve_all([outcome])

    def _write_batches(self, batches: list[_Batch]) -> None:
        if not batches:
            return
        try:
            inserted = self._connection().put_batches([b.row for b in batches], time.time_ns())
        except NotOwner as exc:
            # Runs owned by a connection since lost: this relay writes them no more (their nodes
            # were told to go); the others' batches are tried again on their own.
            rest = [b for b in batches if b.row.run not in exc.runs]
            self._resolve_all([(b.future, None, exc) for b in batches if b.row.run in exc.runs])
            if rest:
                self._write_batches(rest)
            return
        except Exception as exc:  # noqa: BLE001 - the store's errors, or a value it cannot bind
            # Any failure fails this group's batches (their nodes send them again); the thread
            # goes on serving the next ones.
            if isinstance(exc, StoreUnavailable):
                self._lost()
            err = self._failed("store batches", exc)
            self._resolve_all([(b.future, None, err) for b in batches])
            return
        self._worked()
        self.commits += 1
        self.batches_written += sum(inserted)
        self._resolve_all([(b.future, ok, None) for b, ok in zip(batches, inserted)])
