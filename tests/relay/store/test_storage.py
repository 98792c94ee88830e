"""What only the SQLite engine does: its file (WAL, errors naming it), databases of older relays migrated in place.

The behaviour both engines share is tested against each in tests/relay/store/test_store_engines.py."""

from __future__ import annotations

import json
import sqlite3
import uuid

import numpy as np
import pytest

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.wire import encode_batch
from dcuscope.relay.errors import RelayError
from dcuscope.relay.store import sqlite as db
from dcuscope.relay.store.runs import load_runs, load_session

T0 = 1_700_000_000_000_000_000


def payload(run: str, seq: int, events: np.ndarray, compress: bool) -> bytes:
    return encode_batch(run, seq, events, compress)[40:]


def test_errors_name_the_file(tmp_path):
    with pytest.raises(RelayError, match="no such relay database"):
        load_session(tmp_path / "missing.db", 1)
    bad = tmp_path / "bad.db"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(RelayError, match="bad.db"):
        load_session(bad, 1)
    good = tmp_path / "good.db"
    db.connect(good).close()
    with pytest.raises(RelayError, match="no session or run"):
        load_session(good, 3)
    with pytest.raises(RelayError, match="must be a number or a run id"):
        load_session(good, "x; DROP TABLE runs")
    assert sqlite3.connect(good).execute("SELECT count(*) FROM runs").fetchone()[0] == 0


def _older_database(path, schema: int, run: str, events: np.ndarray, clock: dict) -> None:
    """A database as a relay of ``schema`` 1 or 2 wrote it: one run, one batch, its last clock view."""
    ddl = db.SCHEMA[:db.SCHEMA.index("CREATE TABLE IF NOT EXISTS clock_history")]
    if schema == 1:
        ddl = ddl.replace("    clock TEXT NOT NULL DEFAULT '{}',\n    secret TEXT,\n    rejected TEXT\n",
                          "    clock TEXT NOT NULL DEFAULT '{}'\n")
    conn = sqlite3.connect(path)
    conn.executescript(ddl)
    conn.execute("INSERT INTO meta VALUES ('schema', ?)", (str(schema),))
    conn.execute("INSERT INTO sessions (created_ns) VALUES (1)")
    conn.execute("INSERT INTO runs (id, session, node, header, first_seen_ns, last_seen_ns, clock) "
                 "VALUES (?, 1, 'a', ?, 1, 1, ?)", (run, json.dumps(header_for("a", 1).to_dict()), json.dumps(clock)))
    conn.execute("INSERT INTO batches VALUES (?, 0, ?, 0, 1, ?)", (run, len(events), payload(run, 0, events, False)))
    conn.commit()
    conn.close()


@pytest.mark.parametrize("schema", [1, 2])
def test_an_older_database_is_migrated_in_place_and_corrected_by_its_last_estimate(tmp_path, schema):
    path, run = tmp_path / "r.db", uuid.uuid4().hex
    events = synth_events(10, 1, 25.0, T0)
    _older_database(path, schema, run, events, {"applied": "estimate", "correction_ns": 7000, "uncertainty_ns": 90})
    (stored,) = load_runs(path, 1)
    assert np.array_equal(stored.events["ts"], events["ts"] - 7000)
    assert stored.correction.at(int(T0)) == (7000, 90)
    conn = db.connect(path)
    assert conn.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone() == (str(db.SCHEMA_VERSION),)
    assert {"secret", "rejected"} <= {r[1] for r in conn.execute("PRAGMA table_info(runs)")}
    assert db.SqliteDatabase(path).run_history(run) == []


def test_a_relay_database_is_in_wal_mode(tmp_path):
    db.connect(tmp_path / "r.db").close()
    assert sqlite3.connect(tmp_path / "r.db").execute("PRAGMA journal_mode").fetchone()[0] == "wal"
