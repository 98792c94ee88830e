"""SQLite storage: group commits, deduplication, sessions, reading back after a restart."""

from __future__ import annotations

import asyncio
import json
import sqlite3
import uuid

import numpy as np
import pytest

from probes.events import CAPTURE, ORIGIN
from probes.simnode import header_for, synth_events
from probes.wire import encode_batch
from relay import storage as db
from relay.clock import Segment
from relay.errors import RelayError

T0 = 1_700_000_000_000_000_000


def payload(run: str, seq: int, events: np.ndarray, compress: bool) -> bytes:
    return encode_batch(run, seq, events, compress)[40:]


def test_batches_sessions_and_reload(tmp_path):
    path = tmp_path / "r.db"
    h1, h2 = header_for("a", 2), header_for("b", 1)
    ev1 = synth_events(30, 2, 25.0, T0, seed=1)
    ev2 = synth_events(30, 1, 25.0, T0, seed=2)
    r1, r2, r3 = (uuid.uuid4().hex for _ in range(3))

    async def scenario():
        s = db.Storage(path)
        s.start(asyncio.get_running_loop())
        s1, first, secret = await s.call(db.register_run, r1, "a", h1.to_dict(), None, None)
        s2, _, _ = await s.call(db.register_run, r2, "b", h2.to_dict(), s1, None)  # joins the live session
        # A renewed hello, with the secret issued at the first
        assert await s.call(db.register_run, r1, "a", h1.to_dict(), None, secret) == (1, first, None)
        assert s1 == s2 == 1
        halves = np.array_split(ev1, 3)
        results = await asyncio.gather(*(s.put_batch(r1, i, len(p), i == 1, payload(r1, i, p, i == 1))
                                         for i, p in enumerate(halves)))
        assert results == [True, True, True]
        assert await s.put_batch(r1, 1, len(halves[1]), True, payload(r1, 1, halves[1], True)) is False  # resent
        assert await s.put_batch(r2, 0, len(ev2), False, payload(r2, 0, ev2, False))
        await s.call(db.update_run, r2, clock={"correction_ns": 1000}, ended_ns=5, dropped=2, lost=1)
        assert await s.call(db.stored_seqs, r1) == {0, 1, 2}
        with pytest.raises(RelayError, match="belongs to node 'a'"):
            await s.call(db.register_run, r1, "b", h1.to_dict(), None, secret)
        s3, _, _ = await s.call(db.register_run, r3, "a", h1.to_dict(), None, None)  # nothing live: a new session
        assert s3 == 2
        assert s.commits >= 2
        s.stop()

    asyncio.run(scenario())

    runs = db.load_runs(path, 1)
    assert [r.header.node for r in runs] == ["a", "b"]
    assert np.array_equal(runs[0].events, ev1)
    shifted = ev2.copy()
    shifted["ts"] -= 1000
    assert np.array_equal(runs[1].events, shifted) and runs[1].dropped == 2 and runs[1].ended
    assert np.array_equal(db.load_runs(path, 1, corrected=False)[1].events, ev2)
    (h, e), = db.load_session(path, r1[:8])
    assert h.node == "a" and len(e) == len(ev1)
    conn = db.connect(path)
    sessions = db.list_sessions(conn)
    assert [s["session"] for s in sessions] == [2, 1]
    assert [r["events"] for r in sessions[1]["runs"]] == [len(ev1), len(ev2)]
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_errors_name_the_file(tmp_path):
    with pytest.raises(RelayError, match="no such relay database"):
        db.load_session(tmp_path / "missing.db", 1)
    bad = tmp_path / "bad.db"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(RelayError, match="bad.db"):
        db.load_session(bad, 1)
    good = tmp_path / "good.db"
    db.connect(good).close()
    with pytest.raises(RelayError, match="no session or run"):
        db.load_session(good, 3)
    with pytest.raises(RelayError, match="must be a number or a run id"):
        db.load_session(good, "x; DROP TABLE runs")
    assert sqlite3.connect(good).execute("SELECT count(*) FROM runs").fetchone()[0] == 0


def test_a_batch_sqlite_cannot_bind_fails_alone_and_the_writer_keeps_serving(tmp_path):
    """A value sqlite refuses with a non-sqlite exception (OverflowError) used to kill the
    writer thread, and every later put_batch waited for ever."""
    run = uuid.uuid4().hex
    events = synth_events(5, 1, 25.0, T0)

    async def scenario():
        s = db.Storage(tmp_path / "r.db")
        s.start(asyncio.get_running_loop())
        try:
            await s.call(db.register_run, run, "a", header_for("a", 1).to_dict(), None, None)
            with pytest.raises(RelayError, match="cannot store batches: OverflowError"):
                await asyncio.wait_for(s.put_batch(run, 1 << 64, len(events), False, payload(run, 0, events, False)), 10)
            stored = await asyncio.wait_for(s.put_batch(run, 0, len(events), False, payload(run, 0, events, False)), 10)
            assert stored is True and await s.call(db.stored_seqs, run) == {0}
        finally:
            s.stop()
        with pytest.raises(RelayError, match="storage is not running"):
            await s.put_batch(run, 1, len(events), False, payload(run, 1, events, False))

    asyncio.run(scenario())


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
    (stored,) = db.load_runs(path, 1)
    assert np.array_equal(stored.events["ts"], events["ts"] - 7000)
    assert stored.correction.at(int(T0)) == (7000, 90)
    conn = db.connect(path)
    assert conn.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone() == ("3",)
    assert {"secret", "rejected"} <= {r[1] for r in conn.execute("PRAGMA table_info(runs)")}
    assert db.run_history(conn, run) == []


def test_a_stored_history_corrects_each_timestamp_and_a_poisoned_one_falls_back(tmp_path, caplog):
    path, run = tmp_path / "r.db", uuid.uuid4().hex
    events = synth_events(50, 1, 25.0, T0)  # two seconds of frames
    _older_database(path, 2, run, events, {"applied": "estimate", "correction_ns": 9000})
    half = int(T0) + 1_000_000_000
    history = [Segment(int(T0) - 10**9, int(T0), 5000, 0, 100), Segment(half, half, 9000, 1000, 50, 200)]
    conn = db.connect(path)
    db.update_run(conn, run, history=[s.to_dict() for s in history], ended_ns=5)
    db.update_run(conn, run, history=[s.to_dict() for s in history])  # written again: the same rows
    assert db.run_history(conn, run) == history
    (stored,) = db.load_runs(path, run[:8])
    starts = db.frame_starts(events)
    expected = np.where(starts < half, 5000, 9000 + (events["ts"] - half) // 1_000_000)
    assert np.abs(stored.events["ts"] - (events["ts"] - expected)).max() <= 1
    assert (starts < half).sum() > 100 and (starts >= half).sum() > 100  # both segments in use
    assert stored.correction.uncertainties(np.array([half + 10**9]))[0] == 50 + 200
    # A row no relay could have written: the run's last estimate instead, with one warning.
    conn.execute("UPDATE clock_history SET drift_ppb = ? WHERE from_ns = ?", (10**12, half))
    conn.close()
    (stored,) = db.load_runs(path, run[:8])
    assert np.array_equal(stored.events["ts"], events["ts"] - 9000)
    assert [r.message for r in caplog.records if "history" in r.message] == [
        f"run {run}: stored clock history: drift 1000000000000 beyond 1000000; its last estimate is applied instead"]


def test_frame_starts_are_each_frames_earliest_time_in_any_order():
    events = synth_events(30, 3, 25.0, T0, seed=4)
    events = events[np.random.default_rng(0).permutation(len(events))]
    first: dict = {}
    for s, f, t in zip(events["source"].tolist(), events["frame"].tolist(), events["ts"].tolist()):
        first[(s, f)] = min(t, first.get((s, f), t))
    assert db.frame_starts(events).tolist() == [first[(s, f)] for s, f in zip(events["source"].tolist(),
                                                                               events["frame"].tolist())]


def test_capture_times_are_the_cameras_clock_and_stay_as_stored(tmp_path):
    """A node's correction moves its own timestamps, never a frame's capture time (the camera's
    clock, from RTCP sender reports), nor does the capture, the earliest time of a frame, pick
    the estimate the frame is corrected by."""
    path, run = tmp_path / "r.db", uuid.uuid4().hex
    events = synth_events(50, 1, 25.0, T0)
    origins = events[events["point"] == ORIGIN]
    captures = origins.copy()
    captures["point"], captures["stage"] = CAPTURE, 0
    captures["ts"] -= 2 * 10**9  # two seconds earlier: before the second segment's start
    events = np.concatenate([events, captures])
    _older_database(path, 2, run, events, {"applied": "estimate", "correction_ns": 9000})
    half = int(T0) + 1_000_000_000
    history = [Segment(int(T0) - 10**9, int(T0), 5000, 0, 100), Segment(half, half, 9000, 0, 50)]
    conn = db.connect(path)
    db.update_run(conn, run, history=[s.to_dict() for s in history])
    conn.close()
    (stored,) = db.load_runs(path, run[:8])
    assert np.array_equal(stored.events[["source", "frame", "point"]], events[["source", "frame", "point"]])
    is_capture = events["point"] == CAPTURE
    assert np.array_equal(stored.events["ts"][is_capture], captures["ts"])
    moved = events["ts"] - stored.events["ts"]
    starts = db.frame_starts(events, ~is_capture)
    # Each frame by the segment of its own start, not of its capture (all before the second).
    assert np.array_equal(moved[~is_capture], np.where(starts < half, 5000, 9000)[~is_capture])
    assert set(moved[~is_capture].tolist()) == {5000, 9000}


def test_a_run_id_whose_prefix_is_all_digits_is_found_by_it(tmp_path):
    """1 run id in 43 begins with 8 decimal digits: its prefix read as a session number found
    nothing ("no session or run '12812422'", which failed a test at random)."""
    path, run = tmp_path / "r.db", "12812422" + uuid.uuid4().hex[8:]
    events = synth_events(5, 1, 25.0, T0)
    _older_database(path, 2, run, events, {"applied": "none", "correction_ns": 0})
    (stored,) = db.load_runs(path, run[:8])
    assert stored.run == run and np.array_equal(stored.events, events)
    assert [r.run for r in db.load_runs(path, 1)] == [run]  # a session number is still one
    with pytest.raises(RelayError, match="no session or run '999999'"):
        db.load_runs(path, "999999")
