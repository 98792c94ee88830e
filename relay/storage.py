"""SQLite storage of everything nodes ship (WAL mode), queryable after a restart.

Design: a *run* is one run of one node (one ``RelayExporter``: a UUID, the node's trace header,
its event batches). A *session* groups the runs that overlap in time: a new run joins the
session of any run that is live (connected and not ended) when it says hello, else it opens a
new session, so "start the relay, start three nodes" makes one session of three runs. A run
that comes back after a relay restart keeps its session. Sessions are numbered 1, 2, ...

Events are stored as they arrived, one row per batch (the payload blob, compressed or not),
keyed by (run, seq): a resent batch is ignored by the primary key, so every event is stored
exactly once. Timestamps are stored raw (node clock); each run keeps its last clock view and the
history of its clock estimates (``clock_history``), which :func:`load_runs` applies per timestamp.

All writes go through one thread that owns the connection and commits in groups: a batch is
acknowledged to its node only after the transaction holding it committed.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
import logging
import queue
import secrets
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from probes.events import CAPTURE, EVENT_DTYPE, TraceHeader
from probes.wire import decode_payload
from relay.clock import NO_CORRECTION, Correction, Segment, stored_correction
from relay.clockentry import stored_run_correction
from relay.clockmodel import segment_fault
from relay.errors import RelayError

SCHEMA_VERSION = 3
"""2 added runs.secret (hash of the run's resume secret) and runs.rejected (why the relay refused it);
3 added clock_history (each run's clock estimates, each in force from a node time)."""
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
    rejected TEXT
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
"""
HISTORY_COLUMNS = ("from_ns", "ref_ns", "offset_ns", "drift_ppb", "uncertainty_ns", "growth_ppb")
GROUP_LIMIT = 2000
"""Batches committed in one transaction at most."""
RETRY_MS = (250, 5000)
"""What nodes are told to hold their batches for while storage fails: from the first, growing
with how long it has failed (half of it), to the second."""

log = logging.getLogger(__name__)


def connect(path: str | Path, create: bool = True) -> sqlite3.Connection:
    """A connection with the schema in place (WAL mode, normal synchronous)."""
    path = Path(path)
    if not create and not path.exists():
        raise RelayError(f"{path}: no such relay database")
    try:
        conn = sqlite3.connect(str(path), timeout=30, isolation_level=None, check_same_thread=False)
        conn.execute("PRAGMA journal_mode=WAL")
        # NORMAL in WAL mode: a commit survives a crash of the process (kill -9), only an
        # OS crash or power loss may lose the last transactions.
        conn.execute("PRAGMA synchronous=NORMAL")
        conn.executescript(SCHEMA)
        row = conn.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
        if row is not None and row[0] in ("1", "2"):
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
    """Schema 1 or 2 -> 3, in place: runs stored before schema 2 have no resume secret (they cannot
    be resumed); runs stored before 3 have no clock history (their last estimate corrects them),
    its table being made by SCHEMA."""
    conn.execute("BEGIN")
    try:
        columns = {r[1] for r in conn.execute("PRAGMA table_info(runs)")}
        for column in ("secret", "rejected"):
            if column not in columns:
                conn.execute(f"ALTER TABLE runs ADD COLUMN {column} TEXT")
        conn.execute("UPDATE meta SET value = ? WHERE key = 'schema'", (str(SCHEMA_VERSION),))
        conn.execute("COMMIT")
    except BaseException:
        _rollback(conn)
        raise


@dataclass
class _Batch:
    run: str
    seq: int
    count: int
    compressed: bool
    payload: bytes
    future: asyncio.Future


@dataclass
class _Call:
    fn: Callable[..., Any]
    args: tuple
    kwargs: dict
    future: asyncio.Future


class Storage:
    """The relay's database, written by one thread; coroutines wait for their commit."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._conn = connect(self.path)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._worker, name="dcuscope-relay-db", daemon=True)
        self.commits = 0
        self.batches_written = 0
        self._failure: dict | None = None
        """While writes fail: {error, since (epoch s), failed_writes, failed}; None when they work."""

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._thread.start()

    def stop(self) -> None:
        self._queue.put(None)
        self._thread.join(10)
        self._conn.close()

    async def put_batch(self, run: str, seq: int, count: int, compressed: bool, payload: bytes) -> bool:
        """Store a batch; True once committed, False if (run, seq) was already stored.
        Raises :class:`RelayError` if it could not be stored."""
        future = self._future()
        self._queue.put(_Batch(run, seq, count, compressed, payload, future))
        return await future

    async def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Run ``fn(connection, *args, **kwargs)`` in the database thread (its own transaction)."""
        future = self._future()
        self._queue.put(_Call(fn, args, kwargs, future))
        return await future

    @property
    def queued(self) -> int:
        """Writes and calls waiting for the database thread."""
        return self._queue.qsize()

    def health(self) -> dict:
        """{ok} or, while writes fail, {ok: false, error, since, failed_writes, failed {what: count}}
        (for /api/health)."""
        failure = self._failure
        return {"ok": True} if failure is None else dict(failure, ok=False, failed=dict(failure["failed"]))

    def retry_ms(self) -> int:
        """How long a node should hold its batches now (storage failing)."""
        failure = self._failure
        failing_s = time.time() - failure["since"] if failure is not None else 0.0
        return int(min(RETRY_MS[1], max(RETRY_MS[0], failing_s * 500)))

    def _failed(self, what: str, exc: BaseException) -> RelayError:
        # Logged once when writes start failing and once when they work again, not per write
        # (a full disk fails every write, many a second).
        text = f"{type(exc).__name__}: {exc}"
        failure = self._failure
        if failure is None:
            failure = self._failure = {"error": text, "since": time.time(), "failed_writes": 0, "failed": {}}
            log.error("%s: storage failing (%s); batches are held by their nodes until it works again",
                      self.path, text)
        failure["failed_writes"] += 1
        failure["failed"][what] = failure["failed"].get(what, 0) + 1
        failure["error"] = text
        return RelayError(f"{self.path}: cannot {what}: {text}")

    def _worked(self) -> None:
        failure, self._failure = self._failure, None
        if failure is not None:
            log.warning("%s: storage works again after %d failed writes in %.1f s (%s)", self.path,
                        failure["failed_writes"], time.time() - failure["since"], failure["error"])

    def _future(self) -> asyncio.Future:
        # A queue nobody reads would leave the caller waiting for ever.
        if not self._thread.is_alive():
            raise RelayError(f"{self.path}: storage is not running")
        return asyncio.get_running_loop().create_future()

    def _resolve(self, future: asyncio.Future, value: Any = None, error: BaseException | None = None) -> None:
        self._resolve_all([(future, value, error)])

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
        try:
            self._loop.call_soon_threadsafe(settle)
        except RuntimeError:  # the loop closed: nobody waits for these any more
            pass

    def _worker(self) -> None:
        while True:
            item = self._queue.get()
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

    def _run_call(self, call: _Call) -> None:
        try:
            value = call.fn(self._conn, *call.args, **call.kwargs)
        except (sqlite3.Error, OSError) as exc:  # the database failed (a full disk), not the caller
            _rollback(self._conn)
            self._resolve(call.future, error=self._failed(getattr(call.fn, "__name__", "write"), exc))
        except Exception as exc:  # noqa: BLE001 - handed to the awaiting coroutine
            _rollback(self._conn)
            self._resolve(call.future, error=exc)
        else:
            if call.fn in WRITES:
                self._worked()
            self._resolve(call.future, value)

    def _write_batches(self, batches: list[_Batch]) -> None:
        if not batches:
            return
        now = time.time_ns()
        conn = self._conn
        try:
            conn.execute("BEGIN")
            inserted, per_run = [], {}
            for b in batches:
                cur = conn.execute(
                    "INSERT OR IGNORE INTO batches (run, seq, count, compressed, received_ns, data) "
                    "VALUES (?, ?, ?, ?, ?, ?)", (b.run, b.seq, b.count, int(b.compressed), now, b.payload))
                ok = cur.rowcount == 1
                inserted.append(ok)
                per_run[b.run] = per_run.get(b.run, 0) + (b.count if ok else 0)
            conn.executemany("UPDATE runs SET events = events + ?, last_seen_ns = ? WHERE id = ?",
                             [(n, now, run) for run, n in per_run.items()])
            conn.execute("COMMIT")
        except Exception as exc:  # noqa: BLE001 - sqlite's errors, or a value it cannot bind
            # Any failure fails this group's batches (their nodes send them again); the thread
            # goes on serving the next ones.
            _rollback(conn)
            err = self._failed("store batches", exc)
            self._resolve_all([(b.future, None, err) for b in batches])
            return
        self._worked()
        self.commits += 1
        self.batches_written += sum(inserted)
        self._resolve_all([(b.future, ok, None) for b, ok in zip(batches, inserted)])


def _rollback(conn: sqlite3.Connection) -> None:
    try:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
    except sqlite3.Error:  # the writer thread must outlive a failed rollback too
        pass


# --- operations run in the database thread (Storage.call) or on a connection of one's own ---

def register_run(conn: sqlite3.Connection, run: str, node: str, header: dict, live_session: int | None,
                 secret: str | None) -> tuple[int, int, str | None]:
    """Record a run at its (first or renewed) hello; returns its session, first-seen time (ns)
    and, for a new run, the resume secret to hand its node (only its hash is stored).

    A run id already stored must come from the same node with the same stages, and present
    the secret issued at its first hello, else the hello is refused: its batches would be read
    against the wrong stage list, or stored in another node's run.
    """
    now = time.time_ns()
    row = conn.execute("SELECT session, node, header, first_seen_ns, secret FROM runs WHERE id = ?",
                       (run,)).fetchone()
    if row is not None:
        stored = json.loads(row[2])
        if row[1] != node or stored.get("stages") != header.get("stages"):
            raise RelayError(f"run {run} belongs to node {row[1]!r} with other stages")
        if not secret_matches(row[4], secret):
            raise ResumeRefused(f"run {run} exists: resuming it takes the secret issued at its first hello")
        try:
            conn.execute("UPDATE runs SET last_seen_ns = ? WHERE id = ?", (now, run))
        except sqlite3.OperationalError:  # a full disk: the node may still resume its run
            _rollback(conn)
        return int(row[0]), int(row[3]), None
    issued = secrets.token_hex(16)
    conn.execute("BEGIN")
    try:
        session = live_session
        if session is None:
            session = conn.execute("INSERT INTO sessions (created_ns) VALUES (?)", (now,)).lastrowid
        conn.execute("INSERT INTO runs (id, session, node, header, first_seen_ns, last_seen_ns, secret) "
                     "VALUES (?, ?, ?, ?, ?, ?, ?)",
                     (run, session, node, json.dumps(header), now, now, secret_hash(issued)))
        conn.execute("COMMIT")
    except BaseException:
        _rollback(conn)
        raise
    return int(session), now, issued


class ResumeRefused(RelayError):
    """A hello for a stored run without the secret issued at the run's first hello."""


def secret_matches(stored_hash: str | None, presented: str | None) -> bool:
    """Whether ``presented`` is the secret whose hash is stored (constant time); a run stored
    without one (by a relay before schema 2) cannot be resumed."""
    if not stored_hash or not isinstance(presented, str):
        return False
    return hmac.compare_digest(stored_hash, secret_hash(presented))


def secret_hash(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def mark_rejected(conn: sqlite3.Connection, run: str, reason: str) -> None:
    """Keep a run the relay refused apart: sessions and exports leave it out."""
    conn.execute("UPDATE runs SET rejected = ? WHERE id = ? AND rejected IS NULL", (reason[:200], run))


def run_stored(conn: sqlite3.Connection, run: str) -> bool:
    return conn.execute("SELECT 1 FROM runs WHERE id = ?", (run,)).fetchone() is not None


def update_run(conn: sqlite3.Connection, run: str, **fields: Any) -> None:
    """Set ``ended_ns``, ``written``, ``dropped``, ``lost``, ``clock`` (a dict) or ``history`` (the
    run's whole clock history: a list of :meth:`relay.clock.Segment.to_dict`) of a run."""
    allowed = {"ended_ns", "written", "dropped", "lost", "clock", "history"}
    if not fields.keys() <= allowed:
        raise ValueError(f"unknown run fields {sorted(fields.keys() - allowed)}")
    history = fields.pop("history", None)
    values = [json.dumps(v) if k == "clock" else v for k, v in fields.items()]
    conn.execute("BEGIN")
    try:
        if fields:
            conn.execute(f"UPDATE runs SET {', '.join(f'{k} = ?' for k in fields)} WHERE id = ?", (*values, run))
        if history is not None:
            _put_history(conn, run, history)
        conn.execute("COMMIT")
    except BaseException:
        _rollback(conn)
        raise


def _put_history(conn: sqlite3.Connection, run: str, history: list[dict]) -> None:
    """Make the run's stored history ``history``, writing only the rows that changed."""
    stored = {r[0]: r for r in conn.execute(f"SELECT {', '.join(HISTORY_COLUMNS)} FROM clock_history WHERE run = ?",
                                            (run,))}
    rows = [tuple(int(seg[c]) for c in HISTORY_COLUMNS) for seg in history]
    keep = {r[0] for r in rows}
    conn.executemany("DELETE FROM clock_history WHERE run = ? AND from_ns = ?",
                     [(run, t) for t in stored if t not in keep])
    conn.executemany(f"INSERT OR REPLACE INTO clock_history (run, {', '.join(HISTORY_COLUMNS)}) VALUES (?{', ?' * 6})",
                     [(run, *r) for r in rows if stored.get(r[0]) != r])


def run_history(conn: sqlite3.Connection, run: str) -> list[Segment]:
    """A run's stored clock history, oldest first (not checked: see :func:`relay.clockmodel.segment_fault`)."""
    return [Segment(*r) for r in conn.execute(f"SELECT {', '.join(HISTORY_COLUMNS)} FROM clock_history "
                                               "WHERE run = ? ORDER BY from_ns", (run,))]


WRITES = (register_run, update_run, mark_rejected)
"""Calls whose success shows that storage works again."""


def stored_seqs(conn: sqlite3.Connection, run: str) -> set[int]:
    return {r[0] for r in conn.execute("SELECT seq FROM batches WHERE run = ?", (run,))}


def run_events(conn: sqlite3.Connection, run: str) -> np.ndarray:
    """Every stored event of a run, in batch order (raw node timestamps)."""
    parts = [decode_payload(data, bool(c)) for data, c in
             conn.execute("SELECT data, compressed FROM batches WHERE run = ? ORDER BY seq", (run,))]
    return np.concatenate(parts) if parts else np.zeros(0, EVENT_DTYPE)


def list_sessions(conn: sqlite3.Connection) -> list[dict]:
    """Sessions, newest first, each with its runs."""
    runs: dict[int, list[dict]] = {}
    for (rid, session, node, first, last, ended, events, written, dropped, lost, clock) in conn.execute(
            "SELECT id, session, node, first_seen_ns, last_seen_ns, ended_ns, events, written, dropped, lost, clock "
            "FROM runs WHERE rejected IS NULL ORDER BY first_seen_ns"):
        runs.setdefault(session, []).append({
            "run": rid, "node": node, "first_seen_ns": first, "last_seen_ns": last, "ended_ns": ended,
            "events": events, "written": written, "dropped": dropped, "lost": lost, "clock": json.loads(clock)})
    # A session of refused runs only is not a session anybody recorded.
    return [{"session": sid, "created_ns": created, "runs": runs[sid]}
            for sid, created in conn.execute("SELECT id, created_ns FROM sessions ORDER BY id DESC") if sid in runs]


@dataclass
class StoredRun:
    run: str
    session: int
    header: TraceHeader
    events: np.ndarray
    dropped: int
    lost: int
    clock: dict
    ended: bool
    correction: Correction = NO_CORRECTION
    """What brings the run's node timestamps to the relay's clock, per timestamp, and its bound
    (already applied to ``events`` when loaded ``corrected``)."""
    last_ns: int = 0
    """Node time of the run's last event (where its ``clock`` entry is evaluated), 0 without events."""


def load_runs(db: str | Path, session_id: int | str, corrected: bool = True) -> list[StoredRun]:
    """The runs of session ``session_id`` (a number), or the one run whose id starts with it.

    With ``corrected`` each run's timestamps are moved to the relay's clock, each by the estimate
    in force at its time (the run's stored clock history), or, for a run stored without one, by
    the correction its last clock estimate called for (see :func:`relay.clock.correction_ns`).
    """
    conn = connect(db, create=False)
    try:
        key = str(session_id).strip()
        cols = "id, session, header, dropped, lost, clock, ended_ns"
        is_run = len(key) >= 6 and all(c in "0123456789abcdef" for c in key.lower())
        if not key.isdigit() and not is_run:
            raise RelayError(f"{db}: session must be a number or a run id, not {session_id!r}")
        rows = []
        if key.isdigit() and len(key) <= 18:
            rows = conn.execute(f"SELECT {cols} FROM runs WHERE session = ? AND rejected IS NULL "
                                "ORDER BY first_seen_ns", (int(key),)).fetchall()
        if not rows and is_run:  # a run id may begin with digits only (1 in 43 do, over 8 of them)
            rows = conn.execute(f"SELECT {cols} FROM runs WHERE id LIKE ? ORDER BY first_seen_ns",
                                (key.lower() + "%",)).fetchall()
        if not rows:
            raise RelayError(f"{db}: no session or run {session_id!r}")
        out = []
        for rid, session, header, dropped, lost, clock, ended in rows:
            events = run_events(conn, rid)
            last = int(events["ts"].max()) if len(events) else 0
            clock, correction = _run_clock(rid, clock, run_history(conn, rid))
            if corrected and correction.segments and len(events):
                events = events.copy()
                # A capture time is the camera's clock (RTCP sender reports), not the node's: kept.
                node_time = events["point"] != CAPTURE
                events["ts"] = np.where(node_time, correction.correct(events["ts"], frame_starts(events, node_time)),
                                        events["ts"])
            out.append(StoredRun(rid, int(session), TraceHeader.from_dict(json.loads(header)), events,
                                 int(dropped), int(lost), clock, ended is not None, correction, last))
        return out
    except sqlite3.DatabaseError as exc:
        raise RelayError(f"{db}: cannot read session {session_id!r}: {exc}") from exc
    finally:
        conn.close()


def frame_starts(events: np.ndarray, counted: np.ndarray | None = None) -> np.ndarray:
    """Per event, the earliest timestamp of its frame (source, frame) among the ``counted`` events
    (all by default): every event of a frame is corrected by the estimate in force at its start,
    so that a new estimate arriving while a frame went through the pipeline leaves its delays as
    measured on the node's clock."""
    source, frame, ts = events["source"], events["frame"], events["ts"]
    if counted is not None:  # the others never start a frame: they sort after every counted one
        ts = np.where(counted, ts, np.iinfo(np.int64).max)
    order = np.lexsort((frame, source))  # ~1 s for 10 M events (np.unique on the pair: 15 s)
    s, f = source[order], frame[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (s[1:] != s[:-1]) | (f[1:] != f[:-1])
    first = np.minimum.reduceat(ts[order], np.flatnonzero(new))
    out = np.empty(len(ts), dtype=np.int64)
    out[order] = first[np.cumsum(new) - 1]
    return out


def _run_clock(run: str, text: str, history: list[Segment]) -> tuple[dict, Correction]:
    """A stored run's clock view and the correction to apply: its history of estimates when its
    last view applied an estimate, else that view's correction. A correction no relay could have
    computed (written by an older relay from a forged sample, or edited) is ignored, with one
    warning and ``ignored`` in the view: the other runs of the session load as usual."""
    try:
        clock = json.loads(text)
    except ValueError:
        clock = None
    shift, fault = stored_correction(clock)
    if fault is not None:
        log.warning("run %s: stored clock %s; its correction is ignored", run, fault)
        clock = clock if isinstance(clock, dict) else {}
        view = dict(clock, applied="ignored", ignored=fault, correction_ns=0, correction_us=0.0)
        return view, Correction("ignored", fault)
    if history and clock.get("applied") == "estimate":
        bad = next((f for f in map(segment_fault, history) if f is not None), None)
        if bad is None:
            return clock, Correction("estimate", "stored history of estimates", tuple(history))
        log.warning("run %s: stored clock history: %s; its last estimate is applied instead", run, bad)
    return clock, stored_run_correction(clock)


def load_session(db: str | Path, session_id: int | str, corrected: bool = True) -> list[tuple[TraceHeader, np.ndarray]]:
    """``[(header, events), ...]`` of every run of a stored session (for ``dcuscope export``)."""
    return [(r.header, r.events) for r in load_runs(db, session_id, corrected)]
