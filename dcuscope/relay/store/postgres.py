"""The PostgreSQL engine (``--db postgresql://USER@HOST/DB``): one store for any number of relays.

Same tables and meaning as :mod:`dcuscope.relay.store.sqlite`. What a shared store adds:

- **Owners: leases with fencing.** A run is written only by the relay that owns it. Owning is
  holding the run's row in ``leases``: an owner (the relay process), a generation and an expiry
  in PostgreSQL's own time (``clock_timestamp()``), ``LEASE_S`` after the owner last renewed it
  (:meth:`PostgresDatabase.renew`, every ``relay.store.base.RENEW_S``). Another relay may take a run whose lease
  expired: a relay that froze (SIGSTOP, a paused VM) or lost its store holds nothing hostage for
  more than ``LEASE_S``, though its connection, and everything it held, may stay open. Taking a
  run adds one to its generation, the *fencing token*: every write of a run (batches, run fields,
  fleet rows) checks, in its own transaction, that the lease is still the writer's with the
  generation it took (:meth:`PostgresDatabase._fence`, rows locked ``FOR SHARE`` so that a
  takeover waits for the write in progress, never the other way round), and is refused whole
  with :class:`NotOwner` otherwise. A relay that wakes up after its leases were taken can thus
  store nothing more for those runs.

  The fast path: the owner also holds a session-level advisory lock on the run
  (``pg_try_advisory_lock`` on a key from its UUID), which PostgreSQL releases when its connection
  ends. A lease whose owner held the lock and no longer does (the relay was killed, or its
  connection died and PostgreSQL noticed) may be taken at once, without waiting for the expiry.
  Relay connections end a transaction left idle (``IDLE_IN_TRANSACTION_MS``: a relay frozen
  mid-transaction holds no row lock for long) and give up on a dead network within
  ``TCP_USER_TIMEOUT_MS``.
- **Sessions decided in the store.** A new run joins the session of a run that is owned by some
  relay and has not ended; the check and the insert are one transaction under a transaction-level
  advisory lock, so two relays taking hellos at once never split a session.
- **Peers.** Every relay's connections carry ``application_name = dcuscope-relay NAME``;
  ``pg_stat_activity`` lists the relays sharing the store (``/api/health``).
- **The fleet's rows.** Table ``fleet``: each relay upserts, once a second, one row per DCU it holds
  (its node view and overview row, :mod:`dcuscope.relay.live.overview`), so that any relay answers
  ``/api/nodes`` and ``/api/overview`` for the whole fleet; a row nobody refreshed for
  ``relay.api.fleet.ROW_TTL_S`` is deleted.

Batches go in with one statement per group (arrays unnested, ``ON CONFLICT DO NOTHING``), their
payloads stored uncompressed by PostgreSQL (they are compressed already or small).

**A store that waits is not a store that hangs.** With ``timeout_s`` (the relay's ``--store-timeout``)
a thread beside the connection cancels a write not answered within it (PostgreSQL's cancel request:
the statement stops, or, if it was committing and waiting for a synchronous standby that is gone,
the wait stops with the transaction committed on the primary only, and PostgreSQL warns so), and the
write raises :class:`StoreTimeout`: its sender sends it again. A cancel is sent under a lock the
transactions take at their end: it never reaches the next transaction, and one that ended by itself
meanwhile is no timeout. A batch whose commit was cancelled, or whose
connection died mid-commit, may thus be stored already: sent again, it conflicts on its
``(run, seq)`` and is stored once (what the relay's writer makes of that:
:mod:`dcuscope.relay.store.writer`).

**Multi-host URLs.** ``--db postgresql://h1:5432,h2:5432/DB?target_session_attrs=read-write`` is
libpq's own: each connection goes to whichever host is the primary then (a standby is read-only and
refused), so a relay whose primary died reconnects, once one is promoted, to the new primary.

A transaction PostgreSQL rolled back for a conflict with another relay's (a deadlock, a
serialization failure: SQLSTATE class 40) is tried again, up to ``CONFLICT_TRIES`` times: it is
not the store failing. psycopg files these errors under ``OperationalError``, which otherwise means
the connection or the server failed, and a relay whose store fails lets its nodes go.
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from contextlib import nullcontext
from typing import Any

import psycopg

from dcuscope.relay.errors import RelayError
from dcuscope.relay.urls import redact
from dcuscope.relay.store.base import (HISTORY_COLUMNS, LEASE_S, SCHEMA_VERSION, BatchRow, Database, NotOwner,
                                       StoreTimeout, StoreUnavailable, check_resume, secret_hash)

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS sessions (id BIGSERIAL PRIMARY KEY, created_ns BIGINT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    session BIGINT NOT NULL REFERENCES sessions(id),
    node TEXT NOT NULL,
    header TEXT NOT NULL,
    first_seen_ns BIGINT NOT NULL,
    last_seen_ns BIGINT NOT NULL,
    ended_ns BIGINT,
    events BIGINT NOT NULL DEFAULT 0,
    written BIGINT,
    dropped BIGINT NOT NULL DEFAULT 0,
    lost BIGINT NOT NULL DEFAULT 0,
    clock TEXT NOT NULL DEFAULT '{}',
    secret TEXT,
    rejected TEXT,
    lock_key BIGINT NOT NULL,
    rolled_lost BIGINT NOT NULL DEFAULT 0
);
ALTER TABLE runs ADD COLUMN IF NOT EXISTS rolled_lost BIGINT NOT NULL DEFAULT 0;
CREATE TABLE IF NOT EXISTS leases (
    run TEXT PRIMARY KEY,
    owner TEXT NOT NULL,
    generation BIGINT NOT NULL,
    expires TIMESTAMPTZ NOT NULL,
    locked BOOLEAN NOT NULL
);
CREATE INDEX IF NOT EXISTS runs_by_session ON runs(session);
CREATE INDEX IF NOT EXISTS runs_open ON runs(lock_key) WHERE ended_ns IS NULL;
CREATE TABLE IF NOT EXISTS batches (
    run TEXT NOT NULL,
    seq BIGINT NOT NULL,
    count INTEGER NOT NULL,
    compressed BOOLEAN NOT NULL,
    received_ns BIGINT NOT NULL,
    data BYTEA NOT NULL,
    PRIMARY KEY (run, seq)
);
ALTER TABLE batches ALTER COLUMN data SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS clock_history (
    run TEXT NOT NULL,
    from_ns BIGINT NOT NULL,
    ref_ns BIGINT NOT NULL,
    offset_ns BIGINT NOT NULL,
    drift_ppb BIGINT NOT NULL,
    uncertainty_ns BIGINT NOT NULL,
    growth_ppb BIGINT NOT NULL,
    PRIMARY KEY (run, from_ns)
);
CREATE TABLE IF NOT EXISTS segments (
    run TEXT NOT NULL,
    first_seq BIGINT NOT NULL,
    last_seq BIGINT NOT NULL,
    count BIGINT NOT NULL,
    first_ns BIGINT NOT NULL,
    last_ns BIGINT NOT NULL,
    data BYTEA NOT NULL,
    PRIMARY KEY (run, first_seq)
);
ALTER TABLE segments ALTER COLUMN data SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS rollups (
    node TEXT NOT NULL,
    width_ns BIGINT NOT NULL,
    start_ns BIGINT NOT NULL,
    stage TEXT NOT NULL,
    run TEXT NOT NULL,
    incomplete BIGINT NOT NULL,
    drops BIGINT NOT NULL,
    lost BIGINT NOT NULL,
    delay BYTEA NOT NULL,
    service BYTEA NOT NULL,
    wait BYTEA NOT NULL,
    PRIMARY KEY (node, width_ns, start_ns, stage, run)
);
CREATE TABLE IF NOT EXISTS fleet (
    node TEXT PRIMARY KEY,
    run TEXT NOT NULL,
    relay TEXT NOT NULL,
    updated_ns BIGINT NOT NULL,
    view TEXT NOT NULL,
    row TEXT NOT NULL
);
"""
LOCKS = 0x64637573  # "dcus": the first key of the two-key advisory locks below
SCHEMA_LOCK = (LOCKS, 1)
"""Held while a relay creates or migrates the schema (relays starting together)."""
SESSION_LOCK = (LOCKS, 2)
"""Held while a relay decides a new run's session."""
COMPACTION_LOCKS = LOCKS + 1
"""The first key of a run's compaction lock (the second: 31 bits of its UUID): two-key advisory locks
never meet the one-key ones of the runs' owners."""
HELD_RUNS = "SELECT run FROM leases WHERE expires > clock_timestamp()"
"""Runs some relay owns now (their lease has not expired)."""
TAKE_LOCK_TIMEOUT_MS = 1000
"""The longest a takeover waits for a row lock (a write of the owner in progress): it is told to
come back later instead."""
IDLE_IN_TRANSACTION_MS = 3000
"""PostgreSQL ends a relay's session left idle inside a transaction this long (the relay froze
mid-write): its row locks and advisory locks go with it."""
GENERIC_PLANS = "force_generic_plan"
"""A relay's writer plans a prepared statement once per session. Left to choose, PostgreSQL plans
:data:`PUT_BATCHES` again at every execution (with its arrays' lengths known each custom plan looks
cheaper than the generic one), and that planning costs the server ~0.3 ms a round, as much as
the rows (docs/benchmarks-log.md, issue 50, third step). The writer's statements all find rows by key; the
relay's readers (stored sessions, history) open connections of their own, planned as PostgreSQL chooses."""
TCP_USER_TIMEOUT_MS = 3000
"""A relay's connection whose sent data goes unacknowledged this long is dead (a network cut)."""
CONNECT_TIMEOUT_S = 3
WATCH_S = 0.1
"""How often the thread bounding the writes (``timeout_s``) looks at the one in progress."""
ROLLED_BACK = "40"
"""SQLSTATE class of a transaction rolled back for a conflict (40001 serialization, 40P01 deadlock)."""
CONFLICT_TRIES = 5
"""Tries of a transaction rolled back for a conflict with another relay's (a deadlock)."""
CONFLICT_PAUSE_S = 0.01
"""Pause before the next try, times the number of the try (the other transaction finishes meanwhile)."""
APPLICATION = "dcuscope-relay"
WAITING_FOR_STANDBY = "waiting for the store's synchronous standby"
UNCONFIRMED_S = 120.0
"""How long a relay process remembers the secret of a new run whose registration failed without
saying whether it was stored (:data:`_UNCONFIRMED`)."""
_UNCONFIRMED: dict[str, tuple[str, float]] = {}
"""Run -> (the secret issued at its first hello, until when: monotonic) for registrations whose commit
was cancelled or whose connection was lost mid-commit: stored perhaps, their secret never reached the
node. The node's hello again, without a secret, gets that secret from the process that issued it, not
a refusal for lacking one. Process-wide: a relay reconnecting opens a new connection."""

log = logging.getLogger(__name__)


class _Conflict(Exception):
    """A transaction rolled back for a conflict with another's (its cause: psycopg's error)."""


def lock_key(run: str) -> int:
    """The advisory lock key of a run: the first 60 bits of its UUID (positive, so that the key
    read back from pg_locks' two 32-bit halves is the same number)."""
    return int(run[:15], 16)


def _compaction_lock(run: str) -> tuple[int, int]:
    return COMPACTION_LOCKS, int(run[:8], 16) & 0x7FFFFFFF


PUT_BATCHES = """
WITH held AS (
    SELECT l.run FROM leases l JOIN unnest(%(ids)s::text[], %(generations)s::bigint[]) AS o(run, generation)
        ON l.run = o.run AND l.generation = o.generation
    WHERE l.owner = %(owner)s FOR SHARE OF l
), stored AS (
    INSERT INTO batches (run, seq, count, compressed, received_ns, data)
    SELECT r, s, c, z, %(now)s, d
    FROM unnest(%(run)s::text[], %(seq)s::bigint[], %(count)s::int[], %(compressed)s::bool[], %(data)b::bytea[])
        AS b(r, s, c, z, d)
    WHERE (SELECT count(*) FROM held) = %(held)s
        AND coalesce((SELECT g.last_seq FROM segments g WHERE g.run = b.r AND g.first_seq <= b.s
                      ORDER BY g.first_seq DESC LIMIT 1), -1) < b.s
    ON CONFLICT DO NOTHING RETURNING run, seq, count
), counted AS (
    UPDATE runs SET events = runs.events + d.n, last_seen_ns = %(now)s
    FROM (SELECT run, sum(count)::bigint AS n FROM stored GROUP BY run) AS d WHERE runs.id = d.run
)
SELECT (SELECT array_agg(run) FROM held), array_agg(run), array_agg(seq) FROM stored
"""
"""A group of batches stored (:meth:`PostgresDatabase.put_batches`): the leases of its runs locked
and checked (the fence), then its rows inserted, none if a lease is not held (an InitPlan, run
before the insert), each once (a batch sent again conflicts and is left out, and so is one a segment
holds: one index probe), then the events
of those inserted added to their runs' counts. The payloads go as a binary parameter (``%b``): psycopg
sends a list in text by default, and a bytea[] in text is hex that the server parses back."""


class PostgresDatabase(Database):
    engine = "postgresql"
    shared = True

    def __init__(self, url: str, name: str = "", owner: str | None = None, lease_s: float = LEASE_S,
                 timeout_s: float | None = None, generic_plans: bool = False) -> None:
        """``owner``: who holds the leases this connection takes (a relay process, the same across
        its reconnections; default: this connection alone); ``lease_s``: how long a lease it takes
        or renews holds; ``timeout_s``: a transaction not answered within it is cancelled
        (:class:`StoreTimeout`; None: waited for as long as it takes); ``generic_plans``: the
        session plans each prepared statement once (:data:`GENERIC_PLANS`), as a relay's writer wants."""
        self.location = redact(url)
        self.lease_s = lease_s
        self.name = name
        self.owner = owner or f"{name or 'relay'} {secrets.token_hex(6)}"
        self.owned: dict[str, int] = {}
        """Runs whose lease this relay took through this connection -> the generation it took."""
        self.locked: set[str] = set()
        """Owned runs whose advisory lock this connection holds (the fast path)."""
        self.conflicts = 0
        """Transactions tried again after a conflict with another relay's."""
        self.timeout_s = timeout_s
        self._started: float | None = None
        """When the transaction in progress started (monotonic; None: none is)."""
        self._cancelled = False
        """Whether the transaction in progress was cancelled for taking longer than ``timeout_s``."""
        self._unconfirmed = False
        """Whether PostgreSQL warned, in the cancelled transaction, that its commit's wait for the
        synchronous standby was cancelled (committed here, not confirmed there)."""
        self._cancelling = threading.Lock()
        """Held while a cancel is sent, and by a transaction at its end: a cancel meant for one
        transaction never stops the next."""
        self._closing = threading.Event()
        try:
            self.conn = psycopg.connect(url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S,
                                        application_name=f"{APPLICATION} {name}".strip()[:63],
                                        tcp_user_timeout=TCP_USER_TIMEOUT_MS, keepalives=1, keepalives_idle=2,
                                        keepalives_interval=1, keepalives_count=2,
                                        options=f"-c idle_in_transaction_session_timeout={IDLE_IN_TRANSACTION_MS}"
                                                + (f" -c plan_cache_mode={GENERIC_PLANS}" if generic_plans else ""))
        except psycopg.Error as exc:
            raise StoreUnavailable(f"{self.location}: cannot connect: {_first_line(exc)}") from exc
        except ValueError as exc:  # psycopg's word for a URL it cannot parse
            raise RelayError(f"{self.location}: not a PostgreSQL URL: {exc}") from exc
        self.conn.add_notice_handler(self._notice)
        if timeout_s is not None:
            threading.Thread(target=self._bound, name="dcuscope-store-timeout", daemon=True).start()
        self._transaction(self._create_schema)

    def _bound(self) -> None:
        """Cancels a transaction running longer than ``timeout_s`` (the thread that runs it is blocked in it)."""
        while not self._closing.wait(min(WATCH_S, self.timeout_s / 4)):
            with self._cancelling:
                started = self._started
                if started is None or self._cancelled or time.monotonic() - started <= self.timeout_s:
                    continue
                self._cancelled = True
                try:
                    self.conn.cancel_safe(timeout=CONNECT_TIMEOUT_S)
                except (psycopg.Error, OSError) as exc:  # the connection is failing: the write will say so
                    log.info("%s: cannot cancel a write: %s", self.location, _first_line(exc))

    def _notice(self, diagnostic: psycopg.errors.Diagnostic) -> None:
        # "canceling wait for synchronous replication due to user request" (its words are localised).
        if self._cancelled and diagnostic.severity_nonlocalized == "WARNING":
            self._unconfirmed = True

    def _create_schema(self, cur: psycopg.Cursor) -> None:
        cur.execute("SELECT pg_advisory_xact_lock(%s, %s)", SCHEMA_LOCK)
        # Only a database without the schema runs its DDL: CREATE INDEX IF NOT EXISTS and ALTER TABLE
        # lock their tables even when there is nothing to do, and every connection a relay opens
        # comes here, so other relays' writes (holding batches, waiting on runs) would deadlock with it.
        cur.execute("SELECT to_regclass('meta') IS NOT NULL")
        if cur.fetchone()[0]:
            cur.execute("SELECT value FROM meta WHERE key = 'schema'")
            row = cur.fetchone()
            if row is not None and row[0] == str(SCHEMA_VERSION):
                return
        cur.execute(SCHEMA)
        cur.execute("SELECT value FROM meta WHERE key = 'schema'")
        row = cur.fetchone()
        if row is None:
            cur.execute("INSERT INTO meta VALUES ('schema', %s)", (str(SCHEMA_VERSION),))
        elif row[0] in ("3", "4"):  # 4 added the leases table, 5 segments and rollups: made by SCHEMA above
            cur.execute("UPDATE meta SET value = %s WHERE key = 'schema'", (str(SCHEMA_VERSION),))
        elif row[0] != str(SCHEMA_VERSION):
            raise RelayError(f"{self.location}: relay database schema {row[0]}, this relay reads {SCHEMA_VERSION}")

    def _transaction(self, fn, block: bool = True) -> Any:
        """``fn(cursor)`` in a transaction, tried again after a conflict with another relay's.
        ``block=False``: ``fn`` runs one statement, its own transaction (autocommit), with no
        BEGIN and COMMIT of their own (two round trips fewer)."""
        # A lost connection, a server shutting down or out of disk is the store's failure; a
        # conflict with another relay's transaction is not: it is tried again.
        for attempt in range(1, CONFLICT_TRIES + 1):
            try:
                return self._once(fn, block)
            except _Conflict as conflict:
                exc = conflict.__cause__
                if attempt == CONFLICT_TRIES:
                    raise StoreUnavailable(f"{self.location}: {type(exc).__name__} {attempt} times in a row: "
                                           f"{_first_line(exc)}") from exc
                self.conflicts += 1
                log.info("%s: %s; trying again", self.location, _first_line(exc))
                time.sleep(CONFLICT_PAUSE_S * attempt)

    def _once(self, fn, block: bool = True) -> Any:
        self._cancelled = self._unconfirmed = False
        self._started = time.monotonic()
        try:
            with self.conn.transaction() if block else nullcontext(), self.conn.cursor() as cur:
                result = fn(cur)
        except psycopg.OperationalError as exc:
            if self._end():
                raise StoreTimeout(f"{self.location}: no answer within {self.timeout_s:g} s (--store-timeout): "
                                   f"cancelled", standby=False) from exc
            if (exc.sqlstate or "").startswith(ROLLED_BACK):
                raise _Conflict() from exc
            raise StoreUnavailable(f"{self.location}: {type(exc).__name__}: {_first_line(exc)}") from exc
        except psycopg.InterfaceError as exc:  # the connection was closed
            self._end()
            raise StoreUnavailable(f"{self.location}: {_first_line(exc)}") from exc
        except BaseException:
            self._end()
            raise
        if self._end() and self._unconfirmed:
            # Cancelled, yet done, with PostgreSQL's warning: the commit's wait for its synchronous
            # standby was ended so, the transaction committed here and not confirmed there.
            raise StoreTimeout(f"{self.location}: {WAITING_FOR_STANDBY}: a commit not confirmed within "
                               f"{self.timeout_s:g} s (--store-timeout)", standby=True)
        return result  # (cancelled as it ended by itself: done all the same)

    def _end(self) -> bool:
        """The transaction in progress ended (once no cancel is being sent): whether it was cancelled."""
        with self._cancelling:
            self._started = None
            return self._cancelled

    def _rows(self, sql: str, args: tuple = ()) -> list[tuple]:
        def query(cur: psycopg.Cursor) -> list[tuple]:
            cur.execute(sql, args)
            return cur.fetchall()
        return self._transaction(query)

    # --- runs ---------------------------------------------------------------------------------

    def register_run(self, run: str, node: str, header: dict, live_session: int | None,
                     secret: str | None, past_ns: int | None = None) -> tuple[int, int, str | None]:
        now = time.time_ns()
        first = past_ns if past_ns is not None else now
        pending = _UNCONFIRMED.get(run)
        pending = pending[0] if pending is not None and pending[1] > time.monotonic() else None
        issued = pending or secrets.token_hex(16)  # a registration tried again issues the same secret

        def register(cur: psycopg.Cursor) -> tuple[int, int, str | None]:
            cur.execute("SELECT session, node, header, first_seen_ns, secret FROM runs WHERE id = %s", (run,))
            row = cur.fetchone()
            if row is not None and secret is None and pending is not None and row[4] == secret_hash(pending):
                # This process registered the run; the node never heard so.
                check_resume(run, row[1], json.loads(row[2]).get("stages"), row[4], node, header.get("stages"), pending)
                return int(row[0]), int(row[3]), pending
            if row is not None:
                check_resume(run, row[1], json.loads(row[2]).get("stages"), row[4], node, header.get("stages"), secret)
                cur.execute("UPDATE runs SET last_seen_ns = %s WHERE id = %s", (now, run))
                return int(row[0]), int(row[3]), None
            cur.execute("SELECT pg_advisory_xact_lock(%s, %s)", SESSION_LOCK)
            live = None
            if past_ns is None:
                # Not a past run being drained (its header says "spooled"): it has a session of its own.
                cur.execute(f"SELECT session FROM runs WHERE ended_ns IS NULL AND rejected IS NULL AND id <> %s "
                            f"AND header NOT LIKE '%%\"spooled\": true%%' "
                            f"AND id IN ({HELD_RUNS}) ORDER BY first_seen_ns DESC LIMIT 1", (run,))
                live = cur.fetchone()
            if live is not None:
                session = int(live[0])
            else:
                cur.execute("INSERT INTO sessions (created_ns) VALUES (%s) RETURNING id", (first,))
                session = int(cur.fetchone()[0])
            cur.execute("INSERT INTO runs (id, session, node, header, first_seen_ns, last_seen_ns, secret, lock_key) "
                        "VALUES (%s, %s, %s, %s, %s, %s, %s, %s)",
                        (run, session, node, json.dumps(header), first, now, secret_hash(issued), lock_key(run)))
            return session, first, issued

        try:
            out = self._transaction(register)
        except StoreUnavailable:
            now_s = time.monotonic()
            for old in [r for r, (_, until) in _UNCONFIRMED.items() if until <= now_s]:
                del _UNCONFIRMED[old]
            _UNCONFIRMED[run] = (issued, now_s + UNCONFIRMED_S)
            raise
        _UNCONFIRMED.pop(run, None)
        return out

    def own_run(self, run: str) -> bool:
        if run in self.owned:
            return True
        key = lock_key(run)

        def take(cur: psycopg.Cursor) -> int | None:
            cur.execute("SET LOCAL lock_timeout = %s" % TAKE_LOCK_TIMEOUT_MS)
            # The advisory lock first: got, no live connection holds it, so an owner that held it is gone.
            cur.execute("SELECT pg_try_advisory_lock(%s)", (key,))
            got = bool(cur.fetchone()[0])
            cur.execute("INSERT INTO leases AS l (run, owner, generation, expires, locked) "
                        "VALUES (%s, %s, 1, clock_timestamp() + make_interval(secs => %s), %s) "
                        "ON CONFLICT (run) DO UPDATE SET owner = EXCLUDED.owner, generation = l.generation + 1, "
                        "expires = EXCLUDED.expires, locked = EXCLUDED.locked "
                        "WHERE l.owner = EXCLUDED.owner OR l.expires <= clock_timestamp() OR (l.locked AND %s) "
                        "RETURNING generation", (run, self.owner, self.lease_s, got, got))
            row = cur.fetchone()
            if row is None and got:
                cur.execute("SELECT pg_advisory_unlock(%s)", (key,))
            if row is not None and got:
                self.locked.add(run)
            return int(row[0]) if row is not None else None

        try:
            generation = self._transaction(take)
        except StoreUnavailable as exc:
            if isinstance(exc.__cause__, psycopg.errors.LockNotAvailable):
                return False  # the owner is writing (or froze mid-write): come back later
            raise
        if generation is None:
            return False
        self.owned[run] = generation
        return True

    def disown_run(self, run: str) -> None:
        generation = self.owned.get(run)
        if generation is None:
            return
        self._rows("UPDATE leases SET expires = '-infinity' WHERE run = %s AND owner = %s AND generation = %s "
                   "RETURNING run", (run, self.owner, generation))
        self._forget({run})

    def renew(self) -> set[str]:
        """Renew every lease this relay holds; returns the runs whose lease another relay took
        meanwhile (they are no longer owned here)."""
        if not self.owned:
            return set()
        runs = list(self.owned)
        kept = {r for (r,) in self._rows(
            "UPDATE leases l SET expires = clock_timestamp() + make_interval(secs => %s) "
            "FROM unnest(%s::text[], %s::bigint[]) AS o(run, generation) "
            "WHERE l.run = o.run AND l.generation = o.generation AND l.owner = %s RETURNING l.run",
            (self.lease_s, runs, [self.owned[r] for r in runs], self.owner))}
        return self._forget(set(runs) - kept)

    def probe(self) -> None:
        # A commit that wrote WAL, which a synchronous standby must confirm (one that only took a
        # transaction id writes none of its own, and never waits: a promoted server still naming
        # a standby that is gone would look healthy). Any user may emit a logical message.
        self._rows("SELECT pg_logical_emit_message(true, 'dcuscope', '')")

    def _forget(self, lost: set[str]) -> set[str]:
        """Runs no longer owned here (given back, or taken by another relay): their advisory locks let go."""
        for run in lost:
            self.owned.pop(run, None)
            if run in self.locked:
                self.locked.discard(run)
                try:
                    self._rows("SELECT pg_advisory_unlock(%s)", (lock_key(run),))
                except StoreUnavailable:  # the connection is gone, and the lock with it
                    pass
        return lost

    def _fence(self, cur: psycopg.Cursor, runs: set[str]) -> None:
        """In a write's transaction: the runs' leases are still this relay's, at the generation it
        took them (row locks held until the commit, so no takeover passes the write); else
        :class:`NotOwner` and the transaction is rolled back."""
        strangers = runs - self.owned.keys()
        if not strangers:
            ids = list(runs)
            cur.execute("SELECT l.run FROM leases l JOIN unnest(%s::text[], %s::bigint[]) AS o(run, generation) "
                        "ON l.run = o.run AND l.generation = o.generation WHERE l.owner = %s FOR SHARE OF l",
                        (ids, [self.owned[r] for r in ids], self.owner))
            strangers = runs - {r for (r,) in cur.fetchall()}
        if strangers:
            raise NotOwner(strangers)

    def _put_history(self, cur: psycopg.Cursor, run: str, history: list[dict]) -> None:
        cur.execute(f"SELECT {', '.join(HISTORY_COLUMNS)} FROM clock_history WHERE run = %s", (run,))
        stored = {r[0]: tuple(r) for r in cur.fetchall()}
        rows = [tuple(int(seg[c]) for c in HISTORY_COLUMNS) for seg in history]
        keep = {r[0] for r in rows}
        gone = [t for t in stored if t not in keep]
        if gone:
            cur.execute("DELETE FROM clock_history WHERE run = %s AND from_ns = ANY(%s)", (run, gone))
        changed = [(run, *r) for r in rows if stored.get(r[0]) != r]
        if changed:
            cur.executemany(f"INSERT INTO clock_history (run, {', '.join(HISTORY_COLUMNS)}) VALUES (%s{', %s' * 6}) "
                            "ON CONFLICT (run, from_ns) DO UPDATE SET "
                            + ", ".join(f"{c} = EXCLUDED.{c}" for c in HISTORY_COLUMNS[1:]), changed)

    # --- batches ------------------------------------------------------------------------------

    def put_batches(self, batches: list[BatchRow], now_ns: int) -> list[bool]:
        """The batches and their runs' counts in one statement, its own transaction: one round
        trip, where a transaction of its own (BEGIN, the fence, the insert, the counts, COMMIT)
        took five, each costing the writer thread more CPU than the rows it carried. The fence is
        the same: the leases are locked FOR SHARE and checked before a row is inserted, and a run
        not held at its generation stores nothing of the group (:class:`NotOwner`)."""
        runs = {b.run for b in batches}
        strangers = runs - self.owned.keys()
        if strangers:
            raise NotOwner(strangers)
        ids = list(runs)

        def insert(cur: psycopg.Cursor) -> tuple[list[str], set[tuple[str, int]]]:
            cur.execute(PUT_BATCHES, {
                "ids": ids, "generations": [self.owned[r] for r in ids], "owner": self.owner, "held": len(ids),
                "now": now_ns, "run": [b.run for b in batches], "seq": [b.seq for b in batches],
                "count": [b.count for b in batches], "compressed": [b.compressed for b in batches],
                "data": [b.payload for b in batches]})
            held, stored_runs, stored_seqs = cur.fetchone()
            return held or [], set(zip(stored_runs or [], map(int, stored_seqs or [])))

        try:
            held, new = self._transaction(insert, block=False)
            if len(held) != len(ids):
                raise NotOwner(runs - set(held))
        except NotOwner as exc:
            self._forget(exc.runs & self.owned.keys())
            raise
        seen: set[tuple[str, int]] = set()
        out = []
        for b in batches:  # a batch queued twice in one group is stored once
            key = (b.run, b.seq)
            out.append(key in new and key not in seen)
            seen.add(key)
        return out

    # --- the fleet's live rows ---------------------------------------------------------------------

    def put_fleet(self, rows: list[tuple[str, str, str, int, str, str]]) -> None:
        """Each relay's rows of the DCUs it holds, (node, run, relay, updated_ns, view JSON, row JSON),
        upserted by node in one transaction: whichever relay holds a node now writes its row. Rows
        of runs whose lease this relay lost are left out (fenced, as every write of a run)."""
        rows = sorted(rows)  # every relay locks rows in one order: two relays' upserts never deadlock

        def upsert(cur: psycopg.Cursor) -> None:
            runs = {r[1] for r in rows}
            try:
                self._fence(cur, runs)
                mine = rows
            except NotOwner as exc:
                mine = [r for r in rows if r[1] not in exc.runs]
                self._fence(cur, {r[1] for r in mine})
            cur.executemany("INSERT INTO fleet (node, run, relay, updated_ns, view, row) VALUES (%s, %s, %s, %s, %s, %s) "
                            "ON CONFLICT (node) DO UPDATE SET run = EXCLUDED.run, relay = EXCLUDED.relay, "
                            "updated_ns = EXCLUDED.updated_ns, view = EXCLUDED.view, row = EXCLUDED.row", mine)
        self._transaction(upsert)

    def fleet_rows(self, since_ns: int) -> list[tuple[str, str, str, int, str, str]]:
        """The rows written since ``since_ns``; older ones (DCUs nobody holds for that long) are deleted."""
        def read(cur: psycopg.Cursor) -> list[tuple]:
            # Rows another relay is writing now are left to a later call (no lock waits, no deadlock).
            cur.execute("DELETE FROM fleet WHERE node IN (SELECT node FROM fleet WHERE updated_ns < %s "
                        "FOR UPDATE SKIP LOCKED)", (since_ns,))
            cur.execute("SELECT node, run, relay, updated_ns, view, row FROM fleet ORDER BY node")
            return cur.fetchall()
        return self._transaction(read)

    # --- retention ----------------------------------------------------------------------------

    def expired_sessions(self, before_ns: int) -> list[int]:
        return [int(r[0]) for r in self._rows(
            f"SELECT session FROM runs GROUP BY session HAVING max(last_seen_ns) < %s "
            f"AND NOT bool_or(ended_ns IS NULL AND id IN ({HELD_RUNS})) ORDER BY session", (before_ns,))]

    def delete_session_part(self, session: int, limit: int) -> int:
        def delete(cur: psycopg.Cursor) -> int:
            for table, key in (("batches", "seq"), ("segments", "first_seq")):
                cur.execute(f"DELETE FROM {table} WHERE (run, {key}) IN (SELECT run, {key} FROM {table} WHERE run IN "
                            "(SELECT id FROM runs WHERE session = %s) LIMIT %s)", (session, limit))
                if cur.rowcount:
                    return cur.rowcount
            cur.execute("DELETE FROM clock_history WHERE run IN (SELECT id FROM runs WHERE session = %s)", (session,))
            n = cur.rowcount
            cur.execute("DELETE FROM leases WHERE run IN (SELECT id FROM runs WHERE session = %s)", (session,))
            n += cur.rowcount
            cur.execute("DELETE FROM runs WHERE session = %s", (session,))
            n += cur.rowcount
            cur.execute("DELETE FROM sessions WHERE id = %s", (session,))
            return n + cur.rowcount

        return self._transaction(delete)

    # --- compaction -----------------------------------------------------------------------------

    def held_elsewhere(self, owner: str) -> set[str]:
        return {r for (r,) in self._rows("SELECT run FROM leases WHERE expires > clock_timestamp() AND owner <> %s",
                                         (owner,))}

    def claim_compaction(self, run: str) -> bool:
        """A lock on compacting ``run`` for this connection (no wait: False if another holds it)."""
        return bool(self._rows("SELECT pg_try_advisory_lock(%s, %s)", _compaction_lock(run))[0][0])

    def release_compaction(self, run: str) -> None:
        try:
            self._rows("SELECT pg_advisory_unlock(%s, %s)", _compaction_lock(run))
        except StoreUnavailable:  # the connection is gone, and the lock with it
            pass

    # --- the connection -----------------------------------------------------------------------

    def describe(self) -> dict:
        relays = self._rows("SELECT application_name, host(client_addr), backend_start FROM pg_stat_activity "
                            "WHERE datname = current_database() AND application_name LIKE %s ORDER BY backend_start",
                            (APPLICATION + "%",))
        names = sorted({name[len(APPLICATION):].strip() or "?" for name, _, _ in relays})
        return {"engine": self.engine, "location": self.location, "relays": names, "owned_runs": len(self.owned),
                "conflicts": self.conflicts}

    def close(self) -> None:
        self._closing.set()
        self.conn.close()


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
