"""``dcuscope db migrate FILE URL``: move a relay's stored sessions from SQLite to PostgreSQL."""

from __future__ import annotations

import argparse
import sys

from core.errors import DcuscopeError


def add_db_parser(sub) -> None:
    db = sub.add_parser("db", help="manage a relay's store (copy an SQLite file into PostgreSQL)")
    actions = db.add_subparsers(dest="action", required=True, metavar="ACTION", help="migrate: copy SQLite into PostgreSQL")
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


def _migrate(args: argparse.Namespace) -> int:
    from relay.store.engines import is_url
    from relay.store.migrate import migrate  # psycopg loads only for this command

    if not is_url(args.target):
        raise DcuscopeError(f"db migrate: the target must be a postgresql:// URL, not {args.target!r}")
    done = migrate(args.source, args.target, lambda line: print(line, file=sys.stderr, flush=True))
    print(f"copied {done.sessions} sessions, {done.runs} runs, {done.batches} batches ({done.bytes / 1e6:.1f} MB); "
          f"{done.skipped} runs already there")
    return 0
