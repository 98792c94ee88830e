"""The stores the relay benchmarks run the relay on: an SQLite file, or a PostgreSQL server of their own.

``--db FILE`` is the relay's own SQLite store: one relay per file, the writes done in the relay's
process (their CPU is the relay's), WAL journal with ``synchronous=NORMAL`` (relay/store/sqlite.py:
a commit is not fsynced, the WAL is at checkpoints). ``--db postgresql://...`` is a store any number
of relays share; here it is Debian's PostgreSQL 15 started by :class:`tests.pgserver.PostgresServer`
in a temporary folder on loopback, its work done in server processes beside the relay's.

:class:`PostgresStore` runs that server durable by default: fsync, synchronous_commit and
full_page_writes on (PostgreSQL's defaults, what users run: every commit waits for its WAL to reach
the disk), unlike the tests' server. ``durable=False`` turns them off as the tests do;
:meth:`PostgresStore.describe` reads back from the server what it runs with, so that the
benchmark says which. :meth:`PostgresStore.cpu_s` is the CPU the whole server used so far (the
postmaster, its live backends and workers, and those that exited), to put the store's work beside
the relay's.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import CannotRun, one_line  # noqa: E402

STORES = ("sqlite", "postgresql")
SQLITE_SETTINGS = ("SQLite file of the relay's own (one relay per file): WAL, synchronous=NORMAL (the relay's "
                   "settings: commits are not fsynced, the WAL is at checkpoints); writes run in the relay process")
ONE_RELAY = "SQLite is one relay per file"
"""Why a run of several relays on SQLite is n/a: the relay refuses --workers on a file, and two
relays on one file are no configuration it supports."""


class PostgresStore:
    """A PostgreSQL server of the benchmark's own; a fresh database per measurement."""

    def __init__(self, durable: bool = True) -> None:
        """Raises CannotRun when PostgreSQL is not installed or does not start."""
        try:
            from tests.pgserver import PostgresServer

            self.server = PostgresServer(durable=durable)
        except (ImportError, RuntimeError) as exc:
            raise CannotRun(f"no PostgreSQL server for --store postgresql: {exc}") from None
        try:
            self.server.start()
        except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
            self.server.close()
            raise CannotRun(f"the PostgreSQL server did not start: {one_line(str(exc))[-400:]}") from None
        self.durable = durable

    def new_database(self) -> str:
        """The URL of a fresh empty database."""
        return self.server.new_database()

    def drop(self, url: str) -> None:
        """Drop the database at ``url`` (its relays stopped): the next measurement starts on a server
        without the last one's tables in its cache or on its disk."""
        import psycopg

        name = url.rsplit("/", 1)[1]
        with psycopg.connect(self.server.url(), autocommit=True) as conn:
            conn.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")

    def describe(self) -> str:
        """The server's version and durability settings, as it reports them."""
        import psycopg

        with psycopg.connect(self.server.url(), autocommit=True) as conn:
            version = conn.execute("SHOW server_version").fetchone()[0]
            shown = {k: conn.execute(f"SHOW {k}").fetchone()[0]
                     for k in ("fsync", "synchronous_commit", "full_page_writes", "wal_sync_method", "shared_buffers")}
        kind = ("durable, PostgreSQL's defaults: a commit waits for its WAL on disk" if self.durable else
                "NOT durable: the tests' settings, nothing waits for the disk")
        return (f"PostgreSQL {version} on 127.0.0.1, data in {self.server.dir} ({kind}): "
                + " ".join(f"{k}={v}" for k, v in shown.items()))

    def cpu_s(self) -> float:
        """CPU seconds (user + system) the server used so far: the postmaster, its children now
        running (backends, WAL writer, checkpointer, ...) and those it reaped."""
        try:
            pid = int((self.server.data / "postmaster.pid").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return 0.0
        tick = os.sysconf("SC_CLK_TCK")
        total = 0
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                fields = Path(entry.path, "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            # fields[0] is the state (field 3 of stat): ppid is fields[1], utime/stime 11/12, cutime/cstime 13/14
            if int(entry.name) == pid:
                total += sum(int(f) for f in fields[11:15])
            elif int(fields[1]) == pid:
                total += int(fields[11]) + int(fields[12])
        return total / tick

    def close(self) -> None:
        self.server.close()
