"""``dcuscope db migrate FILE URL``: copy a relay's SQLite file into a PostgreSQL store.

Everything is copied: sessions (numbered anew, in the same order, after those already in the
target), runs with their headers, counters, clock views and resume secrets (a node may resume
its run on a relay of the new store), refused runs (still kept apart), batches and segments as
stored (compacted or not: the relays of the target compact what is due), their rollups, clock history,
and the rollups of runs whose events retention deleted. Each run is one transaction, so an interrupted copy leaves whole runs; run again, it
copies only the runs the target lacks. The source is only read (a relay may be writing it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.base import HISTORY_COLUMNS
from dcuscope.relay.store.postgres import PostgresDatabase, lock_key
from dcuscope.relay.store.sqlite import connect

COPIED_RUN_COLUMNS = ("id", "node", "header", "first_seen_ns", "last_seen_ns", "ended_ns", "events", "written", "dropped",
               "lost", "clock", "secret", "rejected", "rolled_lost")
BATCH_COLUMNS = ("seq", "count", "compressed", "received_ns", "data")
SEGMENT_COLUMNS = ("first_seq", "last_seq", "count", "first_ns", "last_ns", "data")
ROLLUP_COLUMNS = ("node", "width_ns", "start_ns", "stage", "incomplete", "drops", "lost", "delay", "service", "wait")


@dataclass
class Copied:
    sessions: int = 0
    runs: int = 0
    skipped: int = 0
    """Runs the target already held."""
    batches: int = 0
    segments: int = 0
    rollups: int = 0
    """Rollup rows of runs whose events retention deleted (those of copied runs go with them)."""
    bytes: int = 0


def migrate(source: str | Path, target: str, say: Callable[[str], None] = lambda line: None) -> Copied:
    """Copy SQLite file ``source`` into the PostgreSQL store ``target``; ``say`` hears one line per session."""
    if not Path(source).is_file():
        raise RelayError(f"{source}: no such relay database")
    src = connect(source, create=False)
    dst = PostgresDatabase(target, "migrate")
    done = Copied()
    try:
        sessions = src.execute("SELECT id, created_ns FROM sessions ORDER BY id").fetchall()
        for sid, created in sessions:
            runs = src.execute(f"SELECT {', '.join(COPIED_RUN_COLUMNS)} FROM runs WHERE session = ? ORDER BY first_seen_ns",
                               (sid,)).fetchall()
            have = {r[0] for r in dst.conn.execute("SELECT id FROM runs WHERE id = ANY(%s)", ([r[0] for r in runs],))}
            if not runs or len(have) == len(runs):
                done.skipped += len(runs)
                continue
            target_session = _session_for(dst, have, created)
            before = (done.batches, done.bytes)
            for run in runs:
                if run[0] in have:
                    done.skipped += 1
                    continue
                _copy_run(src, dst, run, target_session, done)
            done.sessions += 1
            say(f"session {sid} -> {target_session}: {len(runs) - len(have)} runs, {done.batches - before[0]} "
                f"batches, {(done.bytes - before[1]) / 1e6:.1f} MB")
        done.rollups += _copy_orphan_rollups(src, dst)
    finally:
        src.close()
        dst.close()
    return done


def _session_for(dst: PostgresDatabase, have: set[str], created_ns: int) -> int:
    """The target session of a source session: the one its runs copied before went to, else a new one."""
    if have:
        row = dst.conn.execute("SELECT session FROM runs WHERE id = ANY(%s) LIMIT 1", (list(have),)).fetchone()
        return int(row[0])
    created = dst.conn.execute("INSERT INTO sessions (created_ns) VALUES (%s) RETURNING id", (created_ns,))
    return int(created.fetchone()[0])


def _copy_run(src, dst: PostgresDatabase, run: tuple, session: int, done: Copied) -> None:
    rid = run[0]
    with dst.conn.transaction():
        dst.conn.execute(f"INSERT INTO runs (session, lock_key, {', '.join(COPIED_RUN_COLUMNS)}) "
                         f"VALUES (%s, %s{', %s' * len(COPIED_RUN_COLUMNS)})", (session, lock_key(rid), *run))
        with dst.conn.cursor().copy(f"COPY batches (run, {', '.join(BATCH_COLUMNS)}) FROM STDIN") as copy:
            for seq, count, compressed, received, data in src.execute(
                    f"SELECT {', '.join(BATCH_COLUMNS)} FROM batches WHERE run = ? ORDER BY seq", (rid,)):
                copy.write_row((rid, seq, count, bool(compressed), received, data))
                done.batches += 1
                done.bytes += len(data)
        with dst.conn.cursor().copy(f"COPY segments (run, {', '.join(SEGMENT_COLUMNS)}) FROM STDIN") as copy:
            for row in src.execute(f"SELECT {', '.join(SEGMENT_COLUMNS)} FROM segments WHERE run = ? ORDER BY first_seq",
                                   (rid,)):
                copy.write_row((rid, *row))
                done.segments += 1
                done.bytes += len(row[-1])
        with dst.conn.cursor().copy(f"COPY rollups (run, {', '.join(ROLLUP_COLUMNS)}) FROM STDIN") as copy:
            for row in src.execute(f"SELECT {', '.join(ROLLUP_COLUMNS)} FROM rollups WHERE run = ?", (rid,)):
                copy.write_row((rid, *row))
        history = src.execute(f"SELECT {', '.join(HISTORY_COLUMNS)} FROM clock_history WHERE run = ?",
                              (rid,)).fetchall()
        if history:
            dst.conn.cursor().executemany(f"INSERT INTO clock_history (run, {', '.join(HISTORY_COLUMNS)}) "
                                          f"VALUES (%s{', %s' * len(HISTORY_COLUMNS)})", [(rid, *h) for h in history])
    done.runs += 1


def _copy_orphan_rollups(src, dst: PostgresDatabase) -> int:
    """The rollups kept longer than their runs (``--retain raw=...,rollups=...``): copied once, each
    row left alone if the target has it."""
    rows = src.execute(f"SELECT run, {', '.join(ROLLUP_COLUMNS)} FROM rollups WHERE run NOT IN (SELECT id FROM runs)")
    with dst.conn.transaction(), dst.conn.cursor() as cur:
        before = cur.execute("SELECT count(*) FROM rollups").fetchone()[0]
        while chunk := rows.fetchmany(5000):
            cur.executemany(f"INSERT INTO rollups (run, {', '.join(ROLLUP_COLUMNS)}) VALUES (%s{', %s' * len(ROLLUP_COLUMNS)}) "
                            "ON CONFLICT DO NOTHING", chunk)
        return cur.execute("SELECT count(*) FROM rollups").fetchone()[0] - before
