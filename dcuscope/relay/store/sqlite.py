"""The SQLite engine: one file in WAL mode, the relay's embedded default (``--db FILE``).

One relay writes a file at a time (its writer thread, :mod:`dcuscope.relay.store.writer`); readers
(``dcuscope stats``/``export``, the stored sessions' API) open connections of their own and read
while it writes (WAL). A store of one relay needs no owners: :meth:`SqliteDatabase.own_run` always
succeeds, and the live session is the one the relay says (it holds every live run).
"""

from __future__ import annotations

import json
import secrets
import sqlite3
import time
from pathlib import Path
from typing import Any

from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.base import (HISTORY_COLUMNS, READS_SCHEMAS, SCHEMA_VERSION, BatchRow, Database, StoreUnavailable, check_resume,
                              secret_hash)

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS sessions (id INTEGER PRIMARY KEY AUTOINCREMENT, created_ns INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    session INTEGER NOT NULL REFERENCES sessions(id),
    node TEXT NOT NULL,
    header TEXT NOT NULL,
    first_seen_ns INTEGER NOT NULL,
    last_seen_ns INTEGER NOT NULL,
    ended_ns INTEGER,
    events INTEGER NOT NULL DEFAULT 0,
    written INTEGER,
    dropped INTEGER NOT NULL DEFAULT 0,
    lost INTEGER NOT NULL DEFAULT 0,
    clock TEXT NOT NULL DEFAULT '{}',
    secret TEXT,
    rejected TEXT,
    rolled_lost INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS runs_by_session ON runs(session);
CREATE TABLE IF NOT EXISTS batches (
    run TEXT NOT NULL,
    seq INTEGER NOT NULL,
    count INTEGER NOT NULL,
    compressed INTEGER NOT NULL,
    received_ns INTEGER NOT NULL,
    data BLOB NOT NULL,
    PRIMARY KEY (run, seq)
);
CREATE TABLE IF NOT EXISTS clock_history (
    run TEXT NOT NULL,
    from_ns INTEGER NOT NULL,
    ref_ns INTEGER NOT NULL,
    offset_ns INTEGER NOT NULL,
    drift_ppb INTEGER NOT NULL,
    uncertainty_ns INTEGER NOT NULL,
    growth_ppb INTEGER NOT NULL,
    PRIMARY KEY (run, from_ns)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS segments (
    run TEXT NOT NULL,
    first_seq INTEGER NOT NULL,
    last_seq INTEGER NOT NULL,
    count INTEGER NOT NULL,
    first_ns INTEGER NOT NULL,
    last_ns INTEGER NOT NULL,
    data BLOB NOT NULL,
    PRIMARY KEY (run, first_seq)
);
CREATE TABLE IF NOT EXISTS rollups (
    node TEXT NOT NULL,
    width_ns INTEGER NOT NULL,
    start_ns INTEGER NOT NULL,
    stage TEXT NOT NULL,
    run TEXT NOT NULL,
    incomplete INTEGER NOT NULL,
    drops INTEGER NOT NULL,
    lost INTEGER NOT NULL,
    delay BLOB NOT NULL,
    service BLOB NOT NULL,
    wait BLOB NOT NULL,
    PRIMARY KEY (node, width_ns, start_ns, stage, run)
) WITHOUT ROWID;
"""
PUT_BATCH = ("INSERT OR IGNORE INTO batches (run, seq, count, compressed, received_ns, data) SELECT ?, ?, ?, ?, ?, ? "
             "WHERE coalesce((SELECT last_seq FROM segments WHERE run = ? AND first_seq <= ? "
             "ORDER BY first_seq DESC LIMIT 1), -1) < ?")
"""A batch stored once: not if stored before (the key), nor if a segment holds it (one index probe)."""
INCREMENTAL = 2
"""``PRAGMA auto_vacuum``'s value for incremental."""
FREE_PAGES_KEPT = 1024
"""Free pages a file keeps for new rows rather than shrink (4 MiB of 4 KiB pages)."""


def connect(path: str | Path, create: bool = True) -> sqlite3.Connection:
    """A connection with the schema in place (WAL mode, normal synchronous)."""
    path = Path(path)
    if not create and not path.exists():
        raise RelayError(f"{path}: no such relay database")
    try:
        conn = sqlite3.connect(str(path), timeout=30, isolation_level=None, check_same_thread=False)
        # A reader of a store checks that it is one before anything below writes to the file.
        if not create and conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'meta'").fetchone() is None:
            conn.close()
            raise RelayError(f"{path}: not a dcuscope relay database (an SQLite file without dcuscope's tables)")
        # A new file gives the pages compaction frees back on request (relay.store.compaction);
        # an older one keeps them for later rows (setting this needs an empty file, before WAL).
        conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
        conn.execute("PRAGMA journal_mode=WAL")
        # NORMAL in WAL mode: a commit survives a crash of the process (kill -9), only an
        # OS crash or power loss may lose the last transactions.
        conn.execute("PRAGMA synchronous=NORMAL")
        conn.executescript(SCHEMA)
        row = conn.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
        if row is not None and row[0] in READS_SCHEMAS:
            _migrate(conn)
            row = (str(SCHEMA_VERSION),)
        if row is None:
            conn.execute("INSERT OR IGNORE INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
        elif row[0] != str(SCHEMA_VERSION):
            raise RelayError(f"{path}: relay database schema {row[0]}, this relay reads {SCHEMA_VERSION}")
    except sqlite3.DatabaseError as exc:
        raise RelayError(f"{path}: not a usable relay database: {exc}") from exc
    return conn


def _migrate(conn: sqlite3.Connection) -> None:
    """An older schema -> SCHEMA_VERSION, in place: runs stored before schema 2 have no resume
    secret (they cannot be resumed); runs stored before 3 have no clock history (their last estimate
    corrects them); before 5 no segments (their batches are compacted as new ones are). The
    tables are made by SCHEMA."""
    conn.execute("BEGIN")
    try:
        columns = {r[1] for r in conn.execute("PRAGMA table_info(runs)")}
        for column, kind in (("secret", "TEXT"), ("rejected", "TEXT"), ("rolled_lost", "INTEGER NOT NULL DEFAULT 0")):
            if column not in columns:
                conn.execute(f"ALTER TABLE runs ADD COLUMN {column} {kind}")
        conn.execute("UPDATE meta SET value = ? WHERE key = 'schema'", (str(SCHEMA_VERSION),))
        conn.execute("COMMIT")
    except BaseException:
        _rollback(conn)
        raise


def _rollback(conn: sqlite3.Connection) -> None:
    try:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
    except sqlite3.Error:  # the writer thread must outlive a failed rollback too
        pass


class SqliteDatabase(Database):
    engine = "sqlite"
    shared = False

    def __init__(self, path: str | Path, create: bool = True) -> None:
        self.path = Path(path)
        self.location = str(self.path)
        self.conn = connect(self.path, create)

    def _sql(self, sql: str) -> str:
        return sql.replace("%s", "?")

    def _rows(self, sql: str, args: tuple = ()) -> list[tuple]:
        try:
            return self.conn.execute(self._sql(sql), args).fetchall()
        except sqlite3.DatabaseError as exc:
            raise StoreUnavailable(f"{self.path}: cannot read: {exc}") from exc

    def _transaction(self, fn) -> Any:
        # sqlite's own failures (a full disk) are the store's, anything else the caller's.
        conn = self.conn
        try:
            conn.execute("BEGIN")
            value = fn(conn)
            conn.execute("COMMIT")
            return value
        except (sqlite3.Error, OSError) as exc:
            _rollback(conn)
            raise StoreUnavailable(f"{self.path}: {type(exc).__name__}: {exc}") from exc
        except BaseException:
            _rollback(conn)
            raise

    # --- runs ---------------------------------------------------------------------------------

    def register_run(self, run: str, node: str, header: dict, live_session: int | None,
                     secret: str | None, past_ns: int | None = None) -> tuple[int, int, str | None]:
        now = time.time_ns()
        conn = self.conn
        row = conn.execute("SELECT session, node, header, first_seen_ns, secret FROM runs WHERE id = ?",
                           (run,)).fetchone()
        if row is not None:
            check_resume(run, row[1], json.loads(row[2]).get("stages"), row[4], node, header.get("stages"), secret)
            try:
                conn.execute("UPDATE runs SET last_seen_ns = ? WHERE id = ?", (now, run))
            except sqlite3.OperationalError:  # a full disk: the node may still resume its run
                _rollback(conn)
            return int(row[0]), int(row[3]), None
        issued = secrets.token_hex(16)
        first = past_ns if past_ns is not None else now

        def insert(conn: sqlite3.Connection) -> int:
            session = live_session if past_ns is None else None
            if session is None:
                session = conn.execute("INSERT INTO sessions (created_ns) VALUES (?)", (first,)).lastrowid
            conn.execute("INSERT INTO runs (id, session, node, header, first_seen_ns, last_seen_ns, secret) "
                         "VALUES (?, ?, ?, ?, ?, ?, ?)",
                         (run, session, node, json.dumps(header), first, now, secret_hash(issued)))
            return int(session)

        return self._transaction(insert), first, issued

    def own_run(self, run: str) -> bool:
        return True

    def disown_run(self, run: str) -> None:
        pass

    def _put_history(self, conn: sqlite3.Connection, run: str, history: list[dict]) -> None:
        stored = {r[0]: r for r in conn.execute(f"SELECT {', '.join(HISTORY_COLUMNS)} FROM clock_history "
                                                "WHERE run = ?", (run,))}
        rows = [tuple(int(seg[c]) for c in HISTORY_COLUMNS) for seg in history]
        keep = {r[0] for r in rows}
        conn.executemany("DELETE FROM clock_history WHERE run = ? AND from_ns = ?",
                         [(run, t) for t in stored if t not in keep])
        conn.executemany(f"INSERT OR REPLACE INTO clock_history (run, {', '.join(HISTORY_COLUMNS)}) "
                         f"VALUES (?{', ?' * 6})", [(run, *r) for r in rows if stored.get(r[0]) != r])

    # --- batches ------------------------------------------------------------------------------

    def put_batches(self, batches: list[BatchRow], now_ns: int) -> list[bool]:
        def insert(conn: sqlite3.Connection) -> list[bool]:
            inserted, per_run = [], {}
            for b in batches:
                cur = conn.execute(PUT_BATCH, (b.run, b.seq, b.count, int(b.compressed), now_ns, b.payload,
                                               b.run, b.seq, b.seq))
                ok = cur.rowcount == 1
                inserted.append(ok)
                per_run[b.run] = per_run.get(b.run, 0) + (b.count if ok else 0)
            conn.executemany("UPDATE runs SET events = events + ?, last_seen_ns = ? WHERE id = ?",
                             [(n, now_ns, run) for run, n in per_run.items()])
            return inserted

        return self._transaction(insert)

    # --- readers ------------------------------------------------------------------------------

    # --- retention ----------------------------------------------------------------------------

    def expired_sessions(self, before_ns: int) -> list[int]:
        # One relay per file: a run it holds is heard from (last_seen) at least every flush.
        return [r[0] for r in self.conn.execute(
            "SELECT session FROM runs GROUP BY session HAVING max(last_seen_ns) < ? ORDER BY session", (before_ns,))]

    def delete_session_part(self, session: int, limit: int) -> int:
        def delete(conn: sqlite3.Connection) -> int:
            for table in ("batches", "segments"):
                n = conn.execute(f"DELETE FROM {table} WHERE rowid IN (SELECT b.rowid FROM {table} b JOIN runs r "
                                 "ON r.id = b.run WHERE r.session = ? LIMIT ?)", (session, limit)).rowcount
                if n:
                    return n
            n = conn.execute("DELETE FROM clock_history WHERE run IN (SELECT id FROM runs WHERE session = ?)",
                             (session,)).rowcount
            n += conn.execute("DELETE FROM runs WHERE session = ?", (session,)).rowcount
            return n + conn.execute("DELETE FROM sessions WHERE id = ?", (session,)).rowcount

        return self._transaction(delete)

    def give_back_space(self, keep_pages: int = FREE_PAGES_KEPT) -> int:
        """A file with incremental auto-vacuum (made by schema 5 or later) shrinks once a quarter of
        its pages and more than ``keep_pages`` are free (compaction freed them): below that, new
        batches reuse them."""
        if self.conn.execute("PRAGMA auto_vacuum").fetchone()[0] != INCREMENTAL:
            return 0
        free = self.conn.execute("PRAGMA freelist_count").fetchone()[0]
        pages, size = (self.conn.execute(f"PRAGMA {p}").fetchone()[0] for p in ("page_count", "page_size"))
        if not free or free < max(keep_pages, pages // 4 if keep_pages else 0):
            return 0
        self.conn.executescript("PRAGMA incremental_vacuum;")  # execute() steps it once: one page
        self.conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
        return free * size

    # --- the connection -----------------------------------------------------------------------

    def describe(self) -> dict:
        return {"engine": self.engine, "location": self.location}

    def close(self) -> None:
        self.conn.close()
