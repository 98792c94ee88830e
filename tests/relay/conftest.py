"""Fixtures of the relay's tests."""

from __future__ import annotations

import pytest

from tests.pgserver import PostgresServer


@pytest.fixture
def synchronous_store():
    """A PostgreSQL primary whose commits wait for a synchronous standby (made with ``pg_basebackup
    -R`` before any write, tests/pgserver.py): (primary, standby)."""
    primary = PostgresServer(synchronous=True).start()
    standby = None
    try:
        standby = primary.standby()
        yield primary, standby
    finally:
        primary.close()
        if standby is not None:
            standby.close()
