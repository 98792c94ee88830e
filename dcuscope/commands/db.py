"""``dcuscope db migrate FILE URL``: move a relay's stored sessions from SQLite to PostgreSQL;
``dcuscope db compact DB``: compact a store's old batches now."""

from __future__ import annotations

import argparse
import sys
import time

from dcuscope.core.errors import DcuscopeError


def add_db_parser(sub) -> None:
    db = sub.add_parser("db", help="manage a relay's store (copy an SQLite file into PostgreSQL, compact it)")
    actions = db.add_subparsers(dest="action", required=True, metavar="ACTION",
                                help="migrate: copy SQLite into PostgreSQL; compact: compact old batches now")
    p = actions.add_parser(
        "migrate", help="copy every session of an SQLite file into a PostgreSQL store",
        description="Copy every session, run, batch and clock history of a relay's SQLite file into a PostgreSQL "
                    "store that relays share (--db postgresql://...). Sessions are numbered after those already "
                    "there; runs keep their ids and resume secrets. The file is only read. Each run is copied "
                    "whole or not at all: run it again after an interruption and only what is missing is copied.",
        epilog="example:\n  dcuscope db migrate dcuscope.db postgresql://dcuscope@db-host/dcuscope",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", metavar="FILE", help="the relay's SQLite file")
    p.add_argument("target", metavar="URL", help="the PostgreSQL store, postgresql://USER[:PASSWORD]@HOST[:PORT]/DB")
    p.set_defaults(func=_migrate)
    c = actions.add_parser(
        "compact", help="move a store's old batches into compact segments now",
        description="Move every batch stored more than --after seconds ago into compact segments (about 3.5 bytes "
                    "an event instead of 24-32), as relays do by themselves every 30 s (--compact-after): for a store "
                    "written by relays run with --compact-after 0 or before dcuscope compacted. A relay may be "
                    "writing the store meanwhile. Each range of batches is swapped for its segment in one "
                    "transaction: interrupted, nothing is lost or stored twice, and run again it goes on. An SQLite "
                    "file gives the pages freed back to the disk; one made before dcuscope compacted keeps its size "
                    "(new rows reuse them) unless `sqlite3 FILE VACUUM` is run with no relay on it. PostgreSQL's "
                    "autovacuum makes the space of compacted batches reusable in its own time.",
        epilog="examples:\n  dcuscope db compact dcuscope.db\n  dcuscope db compact postgresql://dcuscope@db-host/dcuscope "
               "--after 0",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("db", metavar="FILE|URL", help="the store: a relay's SQLite file or a postgresql:// URL")
    c.add_argument("--after", type=float, default=None, metavar="SECONDS",
                   help="compact batches stored at least this long ago (default: the relay's, 60; 0: all)")
    c.set_defaults(func=_compact)


def _migrate(args: argparse.Namespace) -> int:
    from dcuscope.relay.store.engines import is_url
    from dcuscope.relay.store.migrate import migrate  # psycopg loads only for this command

    if not is_url(args.target):
        raise DcuscopeError(f"db migrate: the target must be a postgresql:// URL, not {args.target!r}")
    done = migrate(args.source, args.target, lambda line: print(line, file=sys.stderr, flush=True))
    print(f"copied {done.sessions} sessions, {done.runs} runs, {done.batches} batches, {done.segments} segments "
          f"({done.bytes / 1e6:.1f} MB), {done.rollups} rollup rows of runs deleted by retention; "
          f"{done.skipped} runs already there")
    return 0


def _compact(args: argparse.Namespace) -> int:
    from dcuscope.relay.store.compaction import COMPACT_AFTER_S, compact
    from dcuscope.relay.store.engines import open_database

    after = COMPACT_AFTER_S if args.after is None else args.after
    if not after >= 0:
        raise DcuscopeError(f"db compact: --after takes seconds, 0 or more, not {args.after:g}")
    database = open_database(args.db, create=False, name="db compact")
    try:
        started = time.monotonic()
        done = compact(database, time.time_ns() - int(after * 1e9), min_events=1,
                       say=lambda line: print(line, file=sys.stderr, flush=True))
        freed = database.give_back_space(keep_pages=0)
    finally:
        database.close()
    ratio = f", {done.bytes_before / done.bytes_after:.1f}x smaller" if done.bytes_after else ""
    print(f"compacted {done.batches} batches ({done.events} events) into {done.segments} segments: "
          f"{done.bytes_before / 1e6:.1f} -> {done.bytes_after / 1e6:.2f} MB{ratio}"
          f"{f'; {freed / 1e6:.1f} MB of file given back' if freed else ''}; "
          f"{done.skipped} ranges left as they were; {time.monotonic() - started:.1f} s")
    return 0
