"""What every storage engine of the relay does: one interface, one module per engine.

A *run* is one run of one node (one ``RelayExporter``: a UUID, the node's trace header, its
event batches). A *session* groups the runs that are live at the same time: a new run joins the
session of a run that is live when it says hello, else it opens a new session, so "start the
relay, start three nodes" makes one session of three runs. A run that comes back after a relay
restart, or on another relay, keeps its session. Sessions are numbered 1, 2, ...

Events are stored as they arrived, one row per batch (the payload blob, compressed or not),
keyed by (run, seq): a resent batch is stored once. Once a batch is old enough, compaction
(:mod:`dcuscope.relay.store.compaction`) moves it with its neighbours into a *segment* (:mod:`dcuscope.relay.store.segment`:
by column, about 3.5 bytes an event where a batch takes 24), one row for a contiguous range of seqs.
Readers read both: :meth:`Database.event_parts` and :meth:`Database.batches_after` give a run's
events by seq whichever row holds them. Timestamps are stored raw (node clock); each
run keeps its last clock view and the history of its clock estimates (``clock_history``), which
:func:`dcuscope.relay.store.runs.load_runs` applies per timestamp.

:class:`Database` is one connection to a store. The engines:

- :mod:`dcuscope.relay.store.sqlite`: a file (``--db FILE``), the embedded default, one relay per file;
- :mod:`dcuscope.relay.store.postgres`: PostgreSQL (``--db postgresql://...``), shared by any number of
  relays. A run is written by the one relay that owns it: ownership is a lease that expires unless
  its owner renews it, and every write carries the generation its owner took (a fencing token), so
  a relay that froze or lost its store can write nothing more once another relay took its runs.

:func:`dcuscope.relay.store.engines.open_database` picks the engine from the ``--db`` value.
"""

from __future__ import annotations

import hashlib
import hmac
import itertools
import json
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from dcuscope.protocol.wire import decode_payload
from dcuscope.relay.clock.correction import Segment
from dcuscope.relay.errors import RelayError
from dcuscope.relay.rollup.compute import FRAME_ROW, HOUR_NS, WIDTHS_NS, Key, Rollup
from dcuscope.relay.rollup.sketch import Sketch
from dcuscope.relay.store.segment import decode as decode_segment
from dcuscope.relay.store.segment import split_batches

SCHEMA_VERSION = 5
"""2 added runs.secret (hash of the run's resume secret) and runs.rejected (why the relay refused it);
3 added clock_history (each run's clock estimates, each in force from a node time); 4 added
PostgreSQL's leases (each run's owner, with an expiry and a fencing generation); 5 added segments
(batches compacted, :mod:`dcuscope.relay.store.compaction`), rollups (:mod:`dcuscope.relay.rollup.compute`) and
runs.rolled_lost."""
READS_SCHEMAS = ("1", "2", "3", "4")
"""Schemas a store is brought to SCHEMA_VERSION from when a relay opens it (the tables and columns
they lack are added; nothing stored is rewritten)."""
LEASE_S = 4.0
"""A shared store: how long a run stays owned after its owner last renewed its lease; another relay
may take it then, at most this long after its owner stopped (froze, or lost the store)."""
RENEW_S = 1.0
"""A shared store: how often a relay renews its leases (a few missed renewals lose nothing)."""
STORE_TIMEOUT_S = 5.0
"""A shared store: the longest a relay waits for a write's answer (``--store-timeout``) before it
cancels the write and tells its sender to send it again (:class:`StoreTimeout`)."""
HISTORY_COLUMNS = ("from_ns", "ref_ns", "offset_ns", "drift_ppb", "uncertainty_ns", "growth_ppb")
RUN_FIELDS = frozenset({"ended_ns", "written", "dropped", "lost", "clock", "history"})
REJECTED_CHARS = 200
RUN_COLUMNS = "id, session, header, dropped, lost, clock, ended_ns"
"""What the readers load of a run (:class:`RunRow`)."""


class ResumeRefused(RelayError):
    """A hello for a stored run without the secret issued at the run's first hello."""


class NotOwner(RelayError):
    """A write for runs this relay does not own (another relay does, or this one lost its store
    connection and with it every run it owned)."""

    def __init__(self, runs: set[str]) -> None:
        super().__init__(f"runs not owned by this relay: {', '.join(sorted(runs))[:200]}")
        self.runs = runs


class StoreUnavailable(RelayError):
    """The store cannot be reached or failed (a full disk, a PostgreSQL restart): what was being
    written is refused whole and written again by whoever sent it."""


class StoreTimeout(StoreUnavailable):
    """A write whose answer did not come within the relay's bound (``--store-timeout``): it was
    cancelled, and whether it was stored is unknown, so it counts as not stored (written again by
    whoever sent it; a batch written twice is stored once). The connection stays: the store answers,
    slowly. ``standby``: the write was committed on the primary and waited for its synchronous
    standby to confirm it (PostgreSQL's ``synchronous_commit`` with a standby that is gone)."""

    def __init__(self, message: str, standby: bool) -> None:
        super().__init__(message)
        self.standby = standby


@dataclass(frozen=True)
class BatchRow:
    run: str
    seq: int
    count: int
    compressed: bool
    payload: bytes


@dataclass(frozen=True)
class RunRow:
    """A stored run as the readers load it."""

    run: str
    session: int
    header: str
    dropped: int
    lost: int
    clock: str
    ended_ns: int | None


class Database(ABC):
    """One connection to a relay store. Writes are transactions: a method returns once what it
    wrote committed. Used by one thread at a time.

    What both engines say in the same SQL is written here once, with ``%s`` placeholders; an
    engine supplies its reads (:meth:`_rows`), its transactions (:meth:`_transaction`) and how
    its driver spells a placeholder (:meth:`_sql`)."""

    engine: str
    """"sqlite" or "postgresql"."""
    location: str
    """Where the store is, for messages (a path, or a URL without its password)."""
    shared: bool
    """Whether several relays may use the store at once (runs need an owner)."""

    # --- what each engine supplies --------------------------------------------------------------

    @abstractmethod
    def _rows(self, sql: str, args: tuple = ()) -> list[tuple]:
        """The rows of a query (``%s`` placeholders); StoreUnavailable if the store failed."""

    @abstractmethod
    def _transaction(self, fn: Callable[[Any], Any]) -> Any:
        """``fn(executor)`` in one transaction (``executor.execute(sql, args)`` in the driver's
        own placeholders: see :meth:`_sql`); StoreUnavailable if the store failed, the caller's
        own errors as they are."""

    def _sql(self, sql: str) -> str:
        """``sql`` with the driver's placeholders (``%s``: psycopg's)."""
        return sql

    @abstractmethod
    def _put_history(self, executor: Any, run: str, history: list[dict]) -> None:
        """Make the run's stored history ``history``, writing only the rows that changed."""

    # --- runs ---------------------------------------------------------------------------------

    @abstractmethod
    def register_run(self, run: str, node: str, header: dict, live_session: int | None,
                     secret: str | None, past_ns: int | None = None) -> tuple[int, int, str | None]:
        """Record a run at its (first or renewed) hello; returns its session, first-seen time (ns)
        and, for a new run, the resume secret to hand its node (only its hash is stored).
        ``past_ns``: a past run drained from a node's spool, started then: a new one is first seen
        then, in a session of its own (never the live one).

        A run id already stored must come from the same node with the same stages, and present
        the secret issued at its first hello, else :class:`RelayError` (:class:`ResumeRefused`):
        its batches would be read against the wrong stage list, or stored in another node's run.
        A new run joins the live session: on a store of one relay the one ``live_session`` names
        (the relay knows), on a shared store the session of a run some relay owns and that has
        not ended, decided in the same transaction as the insert (two relays never split one).
        """

    @abstractmethod
    def own_run(self, run: str) -> bool:
        """Take ownership of ``run`` for this connection: False if another relay owns it."""

    @abstractmethod
    def disown_run(self, run: str) -> None:
        """Give ownership of ``run`` back (its node left, or it ended)."""

    def renew(self) -> set[str]:
        """Keep owning the runs owned here (a shared store's owners renew, see
        :mod:`dcuscope.relay.store.postgres`); returns those another relay took meanwhile."""
        return set()

    def probe(self) -> None:
        """Commit a transaction that writes (what a shared store's synchronous standby must confirm):
        returns once it did, as any write would (:class:`StoreTimeout` past the bound)."""

    def _fence(self, executor: Any, runs: set[str]) -> None:
        """In a write's transaction: :class:`NotOwner` unless ``runs`` are all still owned here
        (a store of one relay: always)."""

    def mark_rejected(self, run: str, reason: str) -> None:
        """Keep a run the relay refused apart: sessions and exports leave it out."""
        self._transaction(lambda x: x.execute(self._sql("UPDATE runs SET rejected = %s WHERE id = %s "
                                                        "AND rejected IS NULL"), (reason[:REJECTED_CHARS], run)))

    def run_stored(self, run: str) -> bool:
        return bool(self._rows("SELECT 1 FROM runs WHERE id = %s", (run,)))

    def update_run(self, run: str, **fields: Any) -> None:
        """Set ``ended_ns``, ``written``, ``dropped``, ``lost``, ``clock`` (a dict) or ``history`` (the
        run's whole clock history: a list of :meth:`dcuscope.relay.clock.correction.Segment.to_dict`); the
        stored history becomes exactly it, only changed rows written."""
        if not fields.keys() <= RUN_FIELDS:
            raise ValueError(f"unknown run fields {sorted(fields.keys() - RUN_FIELDS)}")
        columns = {k: json.dumps(v) if k == "clock" else v for k, v in fields.items() if k != "history"}
        history = fields.get("history")

        def update(executor: Any) -> None:
            self._fence(executor, {run})
            if columns:
                executor.execute(self._sql(f"UPDATE runs SET {', '.join(f'{k} = %s' for k in columns)} WHERE id = %s"),
                                 (*columns.values(), run))
            if history is not None:
                self._put_history(executor, run, history)

        self._transaction(update)

    def run_history(self, run: str) -> list[Segment]:
        """A run's stored clock history, oldest first (not checked: see
        :func:`dcuscope.relay.clock.model.segment_fault`)."""
        return [Segment(*r) for r in self._rows(f"SELECT {', '.join(HISTORY_COLUMNS)} FROM clock_history "
                                                 "WHERE run = %s ORDER BY from_ns", (run,))]

    # --- batches ------------------------------------------------------------------------------

    @abstractmethod
    def put_batches(self, batches: list[BatchRow], now_ns: int) -> list[bool]:
        """Store ``batches`` in one transaction, each run's event count and last-seen time with
        them; per batch True if stored now, False if (run, seq) was stored before. Raises
        :class:`NotOwner` (nothing written) if a run is not owned here."""

    def stored_seqs(self, run: str) -> set[int]:
        """The seqs of a run's stored batches, compacted or not (read in that order: a range compacted
        between the two reads is found in the second)."""
        seqs = {int(r[0]) for r in self._rows("SELECT seq FROM batches WHERE run = %s", (run,))}
        for first, last in self._rows("SELECT first_seq, last_seq FROM segments WHERE run = %s", (run,)):
            seqs.update(range(int(first), int(last) + 1))
        return seqs

    def event_parts(self, run: str) -> list[np.ndarray]:
        """A run's stored events by seq, one array per stored row (a batch or a segment), read in one
        statement: one snapshot, so that a compaction meanwhile neither hides nor doubles a batch."""
        return [_events(segment, data, compressed) for _, segment, data, compressed in self._rows(
            f"{_PARTS} ORDER BY 1", (run, -1, run, -1))]

    def batches_after(self, run: str, seq: int, limit: int) -> list[tuple[int, np.ndarray]]:
        """A run's stored batches after ``seq``, (seq, events), by seq: from at least ``limit`` stored
        rows (fewer at the end), a segment giving back each of its batches."""
        out = []
        for first, segment, data, compressed in self._rows(f"{_PARTS} ORDER BY 1 LIMIT %s",
                                                           (run, seq, run, seq, limit)):
            if not segment:
                out.append((int(first), _events(False, data, compressed)))
                continue
            counts, events = decode_segment(bytes(data))
            out.extend((s, e) for s, e in zip(itertools.count(int(first)), split_batches(counts, events)) if s > seq)
        return out

    # --- compaction (relay.store.compaction) ----------------------------------------------------

    def compaction_due(self, before_ns: int, min_events: int, waited_ns: int | None = None) -> list[tuple[str, bool]]:
        """Runs with batches stored before ``before_ns``, each with whether all of them go (the run
        is quiet: ended, or not heard from since then; or its oldest was stored before ``waited_ns``):
        a run still written otherwise only with ``min_events`` of them at least."""
        rows = self._rows(
            "SELECT b.run, sum(b.count), min(b.received_ns), "
            "max(CASE WHEN r.ended_ns IS NOT NULL OR r.last_seen_ns < %s THEN 1 ELSE 0 END) "
            "FROM batches b JOIN runs r ON r.id = b.run WHERE b.received_ns < %s GROUP BY b.run ORDER BY b.run",
            (before_ns, before_ns))
        due = [(run, bool(quiet) or (waited_ns is not None and int(oldest) < waited_ns), int(events))
               for run, events, oldest, quiet in rows]
        return [(run, whole) for run, whole, events in due if whole or events >= min_events]

    def due_batches(self, run: str, before_ns: int) -> list[tuple[int, int]]:
        """(seq, events) of the run's batches stored before ``before_ns``, by seq."""
        return [(int(s), int(c)) for s, c in self._rows(
            "SELECT seq, count FROM batches WHERE run = %s AND received_ns < %s ORDER BY seq", (run, before_ns))]

    def batch_rows(self, run: str, first: int, last: int) -> list[tuple[int, int, bool, bytes]]:
        """(seq, events, compressed, payload) of the run's batches ``first..last``, by seq."""
        return [(int(s), int(c), bool(z), bytes(d)) for s, c, z, d in self._rows(
            "SELECT seq, count, compressed, data FROM batches WHERE run = %s AND seq BETWEEN %s AND %s ORDER BY seq",
            (run, first, last))]

    def replace_batches(self, run: str, first: int, last: int, count: int, first_ns: int, last_ns: int,
                        data: bytes, node: str = "", rollups: dict[Key, Rollup] | None = None) -> bool:
        """In one transaction: delete batches ``first..last`` of ``run``, store segment ``data`` in
        their place and merge ``rollups`` (of node ``node``) into the stored ones, with the events
        the run lost since its last rollups; nothing (False) unless every batch was still there."""
        class Moved(Exception):
            pass

        def replace(executor: Any) -> None:
            deleted = executor.execute(self._sql("DELETE FROM batches WHERE run = %s AND seq BETWEEN %s AND %s"),
                                       (run, first, last)).rowcount
            if deleted != last - first + 1:
                raise Moved()
            executor.execute(self._sql("INSERT INTO segments (run, first_seq, last_seq, count, first_ns, last_ns, data) "
                                       "VALUES (%s, %s, %s, %s, %s, %s, %s)"),
                             (run, first, last, count, first_ns, last_ns, data))
            if rollups is not None:
                self._merge_rollups(executor, node, run, dict(rollups), last_ns)
        try:
            self._transaction(replace)
        except Moved:
            return False
        return True

    def _merge_rollups(self, executor: Any, node: str, run: str, rollups: dict[Key, Rollup], last_ns: int) -> None:
        """Add ``rollups`` to the run's stored ones, and the events it lost since the last time to its
        frame row of ``last_ns`` (runs.rolled_lost: what rollups hold of its ``lost`` so far)."""
        lost, rolled = executor.execute(self._sql("SELECT lost, rolled_lost FROM runs WHERE id = %s"), (run,)).fetchone()
        if lost > rolled:
            for width in WIDTHS_NS:
                key = (FRAME_ROW, width, last_ns // width * width)
                rollups[key] = rollups.get(key, Rollup()).merge(Rollup(lost=lost - rolled))
            executor.execute(self._sql("UPDATE runs SET rolled_lost = %s WHERE id = %s"), (lost, run))
        for width in WIDTHS_NS:
            starts = [t for _, w, t in rollups if w == width]
            if not starts:
                continue
            for stage, start, *values in executor.execute(self._sql(
                    f"SELECT stage, start_ns, {', '.join(ROLLUP_VALUES)} FROM rollups WHERE node = %s AND width_ns = %s "
                    "AND start_ns BETWEEN %s AND %s AND run = %s"), (node, width, min(starts), max(starts), run)).fetchall():
                key = (stage, width, int(start))
                if key in rollups:
                    rollups[key] = stored_rollup(values).merge(rollups[key])
        executor.executemany(self._sql(
            f"INSERT INTO rollups (node, width_ns, start_ns, stage, run, {', '.join(ROLLUP_VALUES)}) "
            f"VALUES (%s, %s, %s, %s, %s{', %s' * len(ROLLUP_VALUES)}) ON CONFLICT (node, width_ns, start_ns, stage, run) "
            f"DO UPDATE SET {', '.join(f'{c} = excluded.{c}' for c in ROLLUP_VALUES)}"),
            [(node, w, t, stage, run, *rollup_values(r)) for (stage, w, t), r in sorted(rollups.items())])

    def run_node(self, run: str) -> tuple[str, str] | None:
        """(node, header JSON) of a stored run."""
        rows = self._rows("SELECT node, header FROM runs WHERE id = %s", (run,))
        return (rows[0][0], rows[0][1]) if rows else None

    def rollup_rows(self, node: str, width_ns: int, since_ns: int, until_ns: int) -> list[tuple]:
        """(stage, start_ns, run, incomplete, drops, lost, delay, service, wait) of ``node``'s rollups of
        ``width_ns`` starting in ``since_ns..until_ns`` (excluded), by start."""
        return self._rows(f"SELECT stage, start_ns, run, {', '.join(ROLLUP_VALUES)} FROM rollups WHERE node = %s "
                          "AND width_ns = %s AND start_ns >= %s AND start_ns < %s ORDER BY start_ns",
                          (node, width_ns, since_ns, until_ns))

    def rollup_nodes(self) -> list[tuple[str, int, int]]:
        """(node, first start_ns, last start_ns) of every node with rollups."""
        return [(n, int(a), int(b)) for n, a, b in self._rows(
            "SELECT node, min(start_ns), max(start_ns) FROM rollups WHERE width_ns = %s GROUP BY node ORDER BY node",
            (HOUR_NS,))]

    def raw_nodes(self) -> list[tuple[str, int, int]]:
        """(node, first received_ns, last received_ns) of every node with batches not compacted yet."""
        return [(n, int(a), int(b)) for n, a, b in self._rows(
            "SELECT r.node, min(b.received_ns), max(b.received_ns) FROM batches b JOIN runs r ON r.id = b.run "
            "GROUP BY r.node ORDER BY r.node")]

    def delete_rollups_part(self, before_ns: int, limit: int) -> int:
        """Delete up to ``limit`` rollup rows that start before ``before_ns`` (one short transaction)."""
        return self._transaction(lambda x: x.execute(self._sql(
            "DELETE FROM rollups WHERE (node, width_ns, start_ns, stage, run) IN (SELECT node, width_ns, start_ns, "
            "stage, run FROM rollups WHERE start_ns < %s LIMIT %s)"), (before_ns, limit)).rowcount)

    def unrolled_batches(self, node: str, received_since_ns: int) -> list[tuple[str, int, int, int]]:
        """(run, seq, events, received_ns) of ``node``'s batches not compacted yet (their frames not rolled
        up) stored since ``received_since_ns``, by run and seq."""
        return [(r, int(s), int(c), int(t)) for r, s, c, t in self._rows(
            "SELECT b.run, b.seq, b.count, b.received_ns FROM batches b JOIN runs r ON r.id = b.run "
            "WHERE r.node = %s AND b.received_ns >= %s ORDER BY b.run, b.seq", (node, received_since_ns))]

    def unrolled_payloads(self, node: str, received_since_ns: int) -> list[tuple[str, int, bool, bytes]]:
        """(run, seq, compressed, payload) of the batches :meth:`unrolled_batches` lists."""
        return [(r, int(s), bool(z), bytes(d)) for r, s, z, d in self._rows(
            "SELECT b.run, b.seq, b.compressed, b.data FROM batches b JOIN runs r ON r.id = b.run "
            "WHERE r.node = %s AND b.received_ns >= %s ORDER BY b.run, b.seq", (node, received_since_ns))]

    def unrolled_lost(self, run: str) -> int:
        """The events ``run`` lost that its rollups do not hold yet (runs.rolled_lost)."""
        rows = self._rows("SELECT lost - rolled_lost FROM runs WHERE id = %s", (run,))
        return max(0, int(rows[0][0])) if rows else 0

    def newest_compacted_ns(self, node: str, before_ns: int) -> int | None:
        """The newest event time (node clock) of ``node``'s segments that start before ``before_ns``."""
        rows = self._rows("SELECT max(s.last_ns) FROM segments s JOIN runs r ON r.id = s.run "
                          "WHERE r.node = %s AND s.first_ns < %s", (node, before_ns))
        return int(rows[0][0]) if rows and rows[0][0] is not None else None

    def left_raw(self, skip: set[str] = frozenset()) -> tuple[int, int, int, int | None, int | None]:
        """What compaction has not moved yet, but of the runs in ``skip``: (runs, batches, events,
        first and last received_ns)."""
        runs, batches, events, first, last = 0, 0, 0, None, None
        for run, n, c, a, b in self._rows("SELECT run, count(*), sum(count), min(received_ns), max(received_ns) "
                                          "FROM batches GROUP BY run"):
            if run in skip:
                continue
            runs, batches, events = runs + 1, batches + int(n), events + int(c)
            first = int(a) if first is None else min(first, int(a))
            last = int(b) if last is None else max(last, int(b))
        return runs, batches, events, first, last

    def raw_before(self, received_ns: int) -> bool:
        """Whether some batch stored before ``received_ns`` is still raw (not compacted)."""
        return bool(self._rows("SELECT 1 FROM batches WHERE received_ns < %s LIMIT 1", (received_ns,)))

    def held_elsewhere(self, owner: str) -> set[str]:
        """Runs another relay than ``owner`` owns now (a store of one relay: none)."""
        return set()

    def claim_compaction(self, run: str) -> bool:
        """Whether this connection may compact ``run`` now (on a shared store: no other is)."""
        return True

    def release_compaction(self, run: str) -> None:
        pass

    def give_back_space(self, keep_pages: int = 1024) -> int:
        """Give the store's free space back where the engine does it on request, but ``keep_pages``
        pages (0: all); the bytes given."""
        return 0

    # --- readers ------------------------------------------------------------------------------

    def session_runs(self, session: int) -> list[RunRow]:
        """The runs of a session the relay did not refuse, by first-seen time."""
        return [RunRow(*r) for r in self._rows(
            f"SELECT {RUN_COLUMNS} FROM runs WHERE session = %s AND rejected IS NULL ORDER BY first_seen_ns",
            (session,))]

    def runs_with_prefix(self, prefix: str) -> list[RunRow]:
        """Runs whose id starts with ``prefix`` (lower-case hex), by first-seen time."""
        return [RunRow(*r) for r in self._rows(
            f"SELECT {RUN_COLUMNS} FROM runs WHERE id LIKE %s ORDER BY first_seen_ns", (prefix + "%",))]

    def list_sessions(self) -> list[dict]:
        """Sessions, newest first, each with its runs (refused runs left out, and sessions of
        refused runs only); a run's ``stages`` tell which runs are of one pipeline."""
        runs: dict[int, list[dict]] = {}
        for (rid, session, node, first, last, ended, events, written, dropped, lost, clock, header) in self._rows(
                "SELECT id, session, node, first_seen_ns, last_seen_ns, ended_ns, events, written, dropped, lost, "
                "clock, header FROM runs WHERE rejected IS NULL ORDER BY first_seen_ns"):
            runs.setdefault(session, []).append({
                "run": rid, "node": node, "first_seen_ns": first, "last_seen_ns": last, "ended_ns": ended,
                "events": events, "written": written, "dropped": dropped, "lost": lost, "clock": json.loads(clock),
                "stages": json.loads(header).get("stages", [])})
        return [{"session": sid, "created_ns": created, "runs": runs[sid]}
                for sid, created in self._rows("SELECT id, created_ns FROM sessions ORDER BY id DESC") if sid in runs]

    # --- retention ----------------------------------------------------------------------------

    @abstractmethod
    def expired_sessions(self, before_ns: int) -> list[int]:
        """Sessions whose every run was last heard from before ``before_ns`` and none is owned now."""

    @abstractmethod
    def delete_session_part(self, session: int, limit: int) -> int:
        """Delete up to ``limit`` stored batches of ``session`` (one short transaction); once none
        is left, its runs, clock history and the session itself. Returns the rows deleted (0: gone)."""

    # --- the connection -----------------------------------------------------------------------

    @abstractmethod
    def describe(self) -> dict:
        """What /api/health shows of the store: engine, location, and for a shared store the
        relays using it."""

    @abstractmethod
    def close(self) -> None: ...


ROLLUP_VALUES = ("incomplete", "drops", "lost", "delay", "service", "wait")
"""A rollup row's values (its key: node, width_ns, start_ns, stage, run)."""


def rollup_values(r: Rollup) -> tuple:
    return r.incomplete, r.drops, r.lost, r.delay.encode(), r.service.encode(), r.wait.encode()


def stored_rollup(values: tuple | list) -> Rollup:
    incomplete, drops, lost, delay, service, wait = values
    return Rollup(Sketch.decode(bytes(delay)), Sketch.decode(bytes(service)), Sketch.decode(bytes(wait)),
                  int(incomplete), int(drops), int(lost))


_PARTS = ("SELECT seq, 0, data, compressed FROM batches WHERE run = %s AND seq > %s UNION ALL "
          "SELECT first_seq, 1, data, false FROM segments WHERE run = %s AND last_seq > %s")
"""A run's stored rows after a seq: (first seq, whether a segment, data, compressed)."""


def _events(segment: Any, data: bytes, compressed: Any) -> np.ndarray:
    if segment:
        return decode_segment(bytes(data))[1]
    return decode_payload(bytes(data), bool(compressed))


def secret_matches(stored_hash: str | None, presented: str | None) -> bool:
    """Whether ``presented`` is the secret whose hash is stored (constant time); a run stored
    without one (by a relay before schema 2) cannot be resumed."""
    if not stored_hash or not isinstance(presented, str):
        return False
    return hmac.compare_digest(stored_hash, secret_hash(presented))


def secret_hash(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def check_resume(run: str, stored_node: str, stored_stages, stored_secret: str | None, node: str, stages,
                 secret: str | None) -> None:
    """Whether a hello may resume run ``run``, stored or held live (see :meth:`Database.register_run`):
    the same node and stages, and the secret issued at its first hello (else :class:`ResumeRefused`)."""
    if stored_node != node or list(stored_stages or ()) != list(stages or ()):
        raise RelayError(f"run {run} belongs to node {stored_node!r} with other stages")
    if not secret_matches(stored_secret, secret):
        raise ResumeRefused(f"run {run} exists: resuming it takes the secret issued at its first hello")

