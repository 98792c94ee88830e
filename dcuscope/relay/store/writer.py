"""The relay's store, written by one thread: coroutines queue their writes and wait for the commit.

Batches are committed in rounds: the first of a round waits up to ``group_wait_s`` (``GROUP_WAIT_S``)
for others, and all those queued by then are committed in one transaction (at most GROUP_LIMIT), so
that a relay fed by many nodes commits, and wakes its event loop, a few dozen times a second rather
than once a batch. One queued when the store is busy waits no more than that. A batch is
acknowledged to its node only after the transaction holding it committed: a round's outcomes reach
the event loop in one call (:meth:`Storage.queue_batch`'s callbacks, or futures). Other operations
(:meth:`Storage.call`: a method of :class:`dcuscope.relay.store.base.Database`) run in the same thread,
in the order they were queued.

While the store fails (a full disk, PostgreSQL down or restarting) every write is refused with
:class:`dcuscope.relay.errors.RelayError`: nodes hold their batches for :meth:`Storage.retry_ms` and send
them again. One line is logged when writes start failing and one when they work again.

On a shared store the thread also renews this relay's leases every ``RENEW_S``
(:meth:`dcuscope.relay.store.base.Database.renew`). Runs whose lease another relay took (this relay froze,
or could not renew in time), and runs a write was refused for (fenced), are handed to
``on_runs_lost``; a lost connection hands them all (``on_owners_lost``) at once, since this relay
can renew nothing until it reconnects. The relay lets their nodes go: they come back, to this relay
or another, and resume. :meth:`Storage.leases_fresh` says whether the leases are surely still
held now (renewed within ``LEASE_S``), as pushes need.

A write the store does not answer within ``timeout_s`` (``--store-timeout``) is cancelled
(:class:`dcuscope.relay.store.base.StoreTimeout`) and refused like any failed write; the connection
stays. One cancelled while committing, waiting for a synchronous standby that is gone, puts the relay
in the state "waiting for the store's synchronous standby": batches and the writes of hellos are
refused at once (their nodes hold them), and only the lease renewal, once a second, tries the store,
until its commit returns. A batch whose outcome is unknown (its write cancelled, or its connection
lost mid-commit) may be stored already: sent again, the store finds it there, and it is taken as
stored now (fed to the live state then), once.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from dcuscope.core.clocks import NEVER
from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.base import (LEASE_S, RENEW_S, STORE_TIMEOUT_S, BatchRow, Database, NotOwner, StoreTimeout,
                                       StoreUnavailable)
from dcuscope.relay.store.engines import open_database

GROUP_LIMIT = 2000
"""Batches committed in one transaction at most."""
GROUP_WAIT_S = 0.015
"""How long the first batch of a round waits for others to commit with (from when it was queued:
under load, when batches queue while the store writes, no round waits). Nodes ship a batch every
40 ms or so each: 8 nodes make ~3 batches a round rather than 1, a transaction and a wake-up of
the event loop each. It adds as much to the live view's lag, at most."""
RETRY_MS = (250, 5000)
"""What nodes are told to hold their batches for while storage fails: from the first, growing
with how long it has failed (half of it), to the second."""
RECONNECT_S = 1.0
"""A lost shared store is connected to again by the lease renewal, at most this often: meanwhile
writes and calls fail at once (a hello is answered "later" at once, and its node tries another
relay), not each after a connection attempt of its own (up to the connect timeout, on a cut)."""
DESCRIBE_S = 2.0
"""The store's description (the relays sharing it) is refreshed this often."""
WRITES = frozenset({"register_run", "update_run", "mark_rejected", "own_run", "disown_run"})
"""Calls whose success shows that storage works again."""
HELD_WHILE_WAITING = WRITES | {"put_fleet", "fleet_rows"}
"""Calls refused at once while the store waits for its synchronous standby (each would wait out
``--store-timeout``); reads go on."""
UNSURE_LIMIT = 100_000
"""Batches of unknown outcome remembered at most (a store failing for long: the oldest are dropped,
and one of them sent again counts as a duplicate in the live state, stored once all the same)."""

log = logging.getLogger(__name__)


class _Reconnecting(StoreUnavailable):
    """A write refused at once: the store connection was lost and is being opened again."""


class _Waiting(StoreUnavailable):
    """A write refused at once: the store waits for its synchronous standby."""


BatchDone = Callable[[bool | None, BaseException | None], None]
"""Told on the event loop how a queued batch ended: (True: stored now, False: stored before, None) or
(None, the error: not stored)."""


@dataclass
class _Batch:
    row: BatchRow
    done: asyncio.Future | BatchDone
    queued: float
    """When it was queued (monotonic)."""


@dataclass
class _Call:
    name: str | Callable[..., Any]
    args: tuple
    kwargs: dict
    future: asyncio.Future


class Storage:
    """The relay's database, written by one thread; coroutines wait for their commit."""

    def __init__(self, db: str | Path, name: str = "", timeout_s: float = STORE_TIMEOUT_S,
                 group_wait_s: float = GROUP_WAIT_S) -> None:
        self.db = db
        """What ``--db`` named: readers (stored sessions) open their own connections to it."""
        self.name = name
        self.owner = f"{name or 'relay'} {secrets.token_hex(6)}"
        """Who holds this relay's leases on a shared store: the same across its reconnections."""
        self.timeout_s = timeout_s
        self.group_wait_s = group_wait_s
        self._database: Database | None = open_database(db, name=name, owner=self.owner, timeout_s=timeout_s, writer=True)
        self.location = self._database.location
        self.shared = self._database.shared
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._worker, name="dcuscope-relay-db", daemon=True)
        self.commits = 0
        self.batches_written = 0
        self.reconnects = 0
        self.failed_writes = 0
        """Writes and calls refused for the store failing, since the relay started."""
        self.timeouts = {"synchronous_standby": 0, "other": 0}
        """Writes cancelled for taking longer than ``timeout_s``, by cause."""
        self.waiting = False
        """Whether the store waits for its synchronous standby (writes refused at once meanwhile)."""
        self._waiting_for = ""
        """What the write that started the wait said (/api/health's error while waiting: a read failing
        meanwhile for another cause does not hide it)."""
        self._unsure: dict[tuple[str, int], bool] = {}
        """Batches (run, seq) whose write failed without saying whether it was stored, oldest first."""
        self.on_owners_lost: Callable[[], None] | None = None
        """Called on the event loop when the connection that owned this relay's runs was lost."""
        self.on_runs_lost: Callable[[set[str]], None] | None = None
        """Called on the event loop with runs another relay took (their leases, or a fenced write)."""
        self._renewed_at = time.monotonic()
        """When the last renewal that succeeded started (monotonic)."""
        self._tried_at = NEVER
        """When the last connection attempt to a lost store started (monotonic; a machine booted a
        moment ago reads small monotonic times)."""
        self._lost_pending: set[str] = set()
        """Runs a write was refused for (fenced), told with the next renewal's (one word for all)."""
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
        self._queue.put(_Batch(BatchRow(run, seq, count, compressed, payload), future, time.monotonic()))
        return await future

    def queue_batch(self, row: BatchRow, done: BatchDone) -> None:
        """Store a batch, as :meth:`put_batch` does, without a coroutine: ``done`` is called on the event
        loop with its outcome, with the rest of its round's (the ingest settles a round at once)."""
        if not self._thread.is_alive():
            raise RelayError(f"{self.location}: storage is not running")
        self._queue.put(_Batch(row, done, time.monotonic()))

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
        """{ok, engine, location[, relays, leases]} or, while writes fail, also {error, since,
        failed_writes, failed {what: count}} (for /api/health). ``leases`` (a shared store):
        {lease_s, renewed_s_ago, fresh}."""
        failure = self._failure
        out = dict(self._described, reconnects=self.reconnects, timeouts=dict(self.timeouts),
                   waiting_for_standby=self.waiting)
        if self.shared:
            out["leases"] = {"lease_s": LEASE_S, "renewed_s_ago": round(time.monotonic() - self._renewed_at, 2),
                             "fresh": self.leases_fresh()}
        if failure is None:
            return dict(out, ok=True)
        out = {**out, **failure, "ok": False, "failed": dict(failure["failed"])}
        if self.waiting:
            out["error"] = self._waiting_for
        return out

    def leases_fresh(self) -> bool:
        """Whether this relay surely still holds its leases: renewed less than ``LEASE_S`` ago,
        less a renewal's period (a relay that froze longer must not push for runs it may have lost)."""
        return not self.shared or time.monotonic() - self._renewed_at < LEASE_S - RENEW_S

    def retry_ms(self) -> int:
        """How long a node should hold its batches now (storage failing)."""
        failure = self._failure
        failing_s = time.time() - failure["since"] if failure is not None else 0.0
        return int(min(RETRY_MS[1], max(RETRY_MS[0], failing_s * 500)))

    # --- the thread ---------------------------------------------------------------------------

    def _connection(self, reconnect: bool = False) -> Database:
        """The open connection, or a new one after the last was lost (StoreUnavailable if not). A
        shared store is connected to again only by the renewal (``reconnect``); a file always is."""
        if self._database is None:
            since = time.monotonic() - self._tried_at
            if self.shared and (not reconnect or since < RECONNECT_S):
                why = self._failure["error"] if self._failure is not None else "connection lost"
                raise _Reconnecting(f"{self.location}: not connected, connecting again ({why})")
            self._tried_at = time.monotonic()
            self._database = open_database(self.db, name=self.name, owner=self.owner, timeout_s=self.timeout_s, writer=True)
            self.reconnects += 1
            log.info("%s: connected again", self.location)
        return self._database

    def _timed_out(self, exc: StoreTimeout) -> None:
        """A write was cancelled: counted; one cancelled in its commit's wait for the synchronous
        standby holds writes back until a renewal's commit returns (:meth:`_worked`)."""
        self.timeouts["synchronous_standby" if exc.standby else "other"] += 1
        if exc.standby:
            self.waiting = True
            self._waiting_for = str(exc).removeprefix(f"{self.location}: ")

    def _broke(self, exc: StoreUnavailable) -> None:
        """A write failed for the store: a timeout keeps the connection, anything else drops it."""
        if isinstance(exc, StoreTimeout):
            self._timed_out(exc)
        elif not isinstance(exc, _Waiting):
            self._lost()

    def _lost(self) -> None:
        """The connection failed: a shared store's is dropped and opened again at the next write,
        and this relay's runs are let go at once (it cannot renew their leases meanwhile, nor store
        their batches: their nodes go on with another relay); a file's stays (a full disk is not a
        lost file)."""
        if self.shared and self._database is not None:
            try:
                self._database.close()
            except Exception:  # noqa: BLE001 - it is being dropped for failing already
                pass
            self._database = None
            if self.on_owners_lost is not None:
                self._soon(self.on_owners_lost)

    def _runs_lost(self, runs: set[str]) -> None:
        if runs and self.on_runs_lost is not None:
            self._soon(partial(self.on_runs_lost, set(runs)))

    def _fenced(self, runs: set[str]) -> None:
        """A write was refused for ``runs``: the next renewal, at once, tells them with any other
        run lost meanwhile (a relay that wakes up after its leases were taken says so once)."""
        self._lost_pending |= runs

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
        self.failed_writes += 1
        failure["failed"][what] = failure["failed"].get(what, 0) + 1
        if not isinstance(exc, (_Reconnecting, _Waiting)):  # the cause stays said
            failure["error"] = text
        return StoreUnavailable(f"{self.location}: cannot {what}: {text}")

    def _worked(self) -> None:
        self.waiting = False
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

    def _resolve_all(self, outcomes: list[tuple[asyncio.Future | BatchDone, Any, BaseException | None]]) -> None:
        # One wake-up of the event loop per commit, not one per batch.
        def settle() -> None:
            for done, value, error in outcomes:
                if not isinstance(done, asyncio.Future):
                    try:
                        done(None if error is not None else value, error)
                    except Exception:  # noqa: BLE001 - a bug of the caller's: the round's others are told all the same
                        log.exception("storage: a batch's callback failed")
                elif done.done():
                    continue
                elif error is not None:
                    done.set_exception(error)
                else:
                    done.set_result(value)
        self._soon(settle)

    def _worker(self) -> None:
        described = renewed = time.monotonic()
        while True:
            if self.shared and (time.monotonic() - renewed >= RENEW_S or self._lost_pending):
                self._renew()
                renewed = time.monotonic()  # from its end: one waited out (--store-timeout) leaves room for writes
            if time.monotonic() - described >= DESCRIBE_S:
                self._describe()
                described = time.monotonic()
            try:
                item = self._queue.get(timeout=RENEW_S if self.shared else DESCRIBE_S)
            except queue.Empty:
                continue
            if item is None:
                return
            group = self._round(item)
            self._write_batches([g for g in group if isinstance(g, _Batch)])
            for call in (g for g in group if isinstance(g, _Call)):
                self._run_call(call)

    def _round(self, first: _Batch | _Call) -> list[_Batch | _Call]:
        """``first`` and what is queued with it: a batch waits for others until ``group_wait_s`` after
        it was queued; a call, or the limit, ends the wait."""
        group = [first]
        until = first.queued + self.group_wait_s if isinstance(first, _Batch) else 0.0
        while len(group) < GROUP_LIMIT:
            wait = until - time.monotonic()
            try:
                nxt = self._queue.get(timeout=wait) if wait > 0 else self._queue.get_nowait()
            except queue.Empty:
                break
            if nxt is None:
                self._queue.put(None)
                break
            group.append(nxt)
            if isinstance(nxt, _Call):
                until = 0.0
        return group

    def _remember_unsure(self, batches: list[_Batch]) -> None:
        """Batches whose write may have been stored though it failed (cancelled, or its connection
        lost, mid-commit): found stored when sent again, they are new to this relay all the same."""
        for b in batches:
            self._unsure[(b.row.run, b.row.seq)] = True
        while len(self._unsure) > UNSURE_LIMIT:
            del self._unsure[next(iter(self._unsure))]

    def _renew(self) -> None:
        """Renew this relay's leases; hand on the runs another relay took."""
        started = time.monotonic()
        try:
            database = self._connection(reconnect=True)
            if self.waiting:
                database.probe()  # a relay holding no run renews nothing: this asks the standby all the same
            lost = database.renew()
        except StoreUnavailable as exc:
            self._broke(exc)
            self._failed("renew leases", exc)
            return
        self._renewed_at = started
        self._worked()  # the store answered (an idle relay writes nothing else to show it)
        lost, self._lost_pending = lost | self._lost_pending, set()
        self._runs_lost(lost)

    def _describe(self) -> None:
        """What /api/health shows of the store (the relays sharing it come and go)."""
        if self._database is None:
            return
        try:
            self._described = self._database.describe()
        except StoreUnavailable as exc:
            self._broke(exc)
            self._failed("describe the store", exc)

    def _run_call(self, call: _Call) -> None:
        try:
            if self.waiting and call.name in HELD_WHILE_WAITING:
                raise _Waiting(f"{self.location}: {self._waiting_for}")
            database = self._connection()
            fn = getattr(database, call.name) if isinstance(call.name, str) else partial(call.name, database)
            value = fn(*call.args, **call.kwargs)
        except StoreUnavailable as exc:  # the store failed (a full disk, a lost server), not the caller
            self._broke(exc)
            what = call.name if isinstance(call.name, str) else getattr(call.name, "__name__", "write")
            outcome = (call.future, None, self._failed(what, exc))
        except Exception as exc:  # noqa: BLE001 - handed to the awaiting coroutine
            if isinstance(exc, NotOwner):
                self._fenced(exc.runs)
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
            if self.waiting:
                raise _Waiting(f"{self.location}: {self._waiting_for}")
            inserted = self._connection().put_batches([b.row for b in batches], time.time_ns())
        except NotOwner as exc:
            # Runs another relay took (fenced): this relay writes them no more and lets their
            # nodes go; the others' batches are tried again on their own.
            self._fenced(exc.runs)
            rest = [b for b in batches if b.row.run not in exc.runs]
            self._resolve_all([(b.done, None, exc) for b in batches if b.row.run in exc.runs])
            if rest:
                self._write_batches(rest)
            return
        except Exception as exc:  # noqa: BLE001 - the store's errors, or a value it cannot bind
            # Any failure fails this group's batches (their nodes send them again); the thread
            # goes on serving the next ones.
            if isinstance(exc, StoreUnavailable):
                self._broke(exc)
                if not isinstance(exc, (_Waiting, _Reconnecting)):
                    self._remember_unsure(batches)
            err = self._failed("store batches", exc)
            self._resolve_all([(b.done, None, err) for b in batches])
            return
        self._worked()
        if self._unsure:
            inserted = [self._unsure.pop((b.row.run, b.row.seq), False) or ok for b, ok in zip(batches, inserted)]
        self.commits += 1
        self.batches_written += sum(inserted)
        self._resolve_all([(b.done, ok, None) for b, ok in zip(batches, inserted)])
