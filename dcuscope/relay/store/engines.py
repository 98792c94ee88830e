"""Which engine a ``--db`` value names, and a connection to it."""

from __future__ import annotations

from pathlib import Path

from dcuscope.relay.store.base import Database


def is_url(db: str | Path) -> bool:
    return str(db).startswith(("postgresql://", "postgres://"))


def open_database(db: str | Path, create: bool = True, name: str = "", owner: str | None = None,
                  timeout_s: float | None = None, writer: bool = False) -> Database:
    """A connection to the store ``db`` names: a ``postgresql://`` URL, else an SQLite file
    (``create``: made if missing, else :class:`RelayError`). ``name``: the relay's, shown to the
    other relays of a shared store; ``owner``: who holds the runs this connection takes (see
    :class:`dcuscope.relay.store.postgres.PostgresDatabase`); ``timeout_s``: a PostgreSQL store's writes not
    answered within it are cancelled (:class:`dcuscope.relay.store.base.StoreTimeout`; None: never);
    ``writer``: a relay's writer (PostgreSQL: generic plans, see ``PostgresDatabase``)."""
    if is_url(db):
        from dcuscope.relay.store.postgres import PostgresDatabase  # psycopg loads only for PostgreSQL

        return PostgresDatabase(str(db), name, owner, timeout_s=timeout_s, generic_plans=writer)
    from dcuscope.relay.store.sqlite import SqliteDatabase

    return SqliteDatabase(db, create)

