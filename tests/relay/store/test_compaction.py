"""Compaction (relay/store/compaction.py) on each engine: every reader reads a run the same before and
after, by whole run and from any seq; a batch sent again is not stored twice; a missing batch ends
a range; retention and `db migrate` take segments too; a relay killed mid-compaction loses nothing
and stores nothing twice; a relay compacts by itself and `db compact` does on request."""

from __future__ import annotations

import os
import signal
import time
import uuid

import numpy as np
import pytest

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.relay.store.base import BatchRow
from dcuscope.relay.store.compaction import compact, ranges
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.runs import list_sessions, load_runs
from tests.conftest import run_cli
from tests.relay.helpers import RelayProcess, finish_node, get_json, http_status, start_node, wait_for
from tests.relay.store.test_store_engines import T0, execute, payload, store  # noqa: F401 - store: the engines' fixture

BATCH = 200


def write_run(store: str, events: np.ndarray, skip: tuple[int, ...] = (), received_ns: int = 1,
              run: str | None = None) -> tuple[str, list[np.ndarray]]:
    """A run of node "a" whose events are stored in batches of BATCH (odd ones compressed), but for
    the seqs in ``skip``, all received at ``received_ns`` (long ago: due for compaction)."""
    run = run or uuid.uuid4().hex
    parts = [events[i:i + BATCH] for i in range(0, len(events), BATCH)]
    database = open_database(store)
    try:
        assert database.own_run(run)
        database.register_run(run, "a", header_for("a", 2).to_dict(), None, None)
        rows = [BatchRow(run, seq, len(p), seq % 2 == 1, payload(run, seq, p, seq % 2 == 1))
                for seq, p in enumerate(parts) if seq not in skip]
        assert all(database.put_batches(rows, received_ns))
        database.update_run(run, ended_ns=received_ns)
        database.disown_run(run)
    finally:
        database.close()
    return run, parts


def table_rows(store: str, table: str) -> int:
    database = open_database(store)
    try:
        return int(database._rows(f"SELECT count(*) FROM {table}")[0][0])
    finally:
        database.close()


def test_ranges_are_contiguous_and_bounded():
    due = [(0, 5), (1, 5), (2, 5), (4, 5), (5, 5), (9, 100)]
    assert ranges(due, most=12) == [(0, 1, 10), (2, 2, 5), (4, 5, 10), (9, 9, 100)]


def test_every_reader_reads_a_compacted_run_as_before_from_any_seq(store):
    events = synth_events(200, 2, 25.0, T0, seed=4, drop_rate=0.05)  # ~4,800 events, 24 batches
    run, parts = write_run(store, events, skip=(7,))
    before = load_runs(store, run, corrected=False)[0]
    database = open_database(store)
    try:
        reads = {seq: database.batches_after(run, seq, 5) for seq in (-1, 3, 6, 7, 12)}
        done = compact(database, time.time_ns(), min_events=1)
        assert (done.segments, done.batches, done.events) == (2, len(parts) - 1, len(events) - len(parts[7]))
        assert done.bytes_after * 4 < done.bytes_before
        assert table_rows(store, "batches") == 0 and table_rows(store, "segments") == 2
        # A batch sent again is stored once, compacted or not; the missing one still goes in.
        again = [BatchRow(run, s, len(parts[s]), False, payload(run, s, parts[s], False)) for s in (0, 7, 8)]
        assert database.own_run(run)
        assert database.put_batches(again, 2) == [False, True, False]
        assert database.stored_seqs(run) == set(range(len(parts)))
        for seq, first_read in reads.items():
            got = [(s, e) for s, e in database.batches_after(run, seq, 5) if s != 7]  # 7 was not there before
            assert [s for s, _ in got[:len(first_read)]] == [s for s, _ in first_read]
            for (s, a), (_, b) in zip(got, first_read):
                assert np.array_equal(a, b) and np.array_equal(a, parts[s])
    finally:
        database.close()
    (after,) = load_runs(store, run, corrected=False)
    assert np.array_equal(before.events, np.delete(events, np.s_[7 * BATCH:8 * BATCH]))
    assert np.array_equal(after.events, events)  # by seq: 7, stored last, reads in its place


def test_a_live_run_waits_for_a_large_range_or_a_while_and_a_quiet_one_does_not(store):
    """A run still written waits for a range of ``min_events``, or until its oldest due batch was
    stored before ``waited_ns`` (the relay's: LIVE_WAIT_S ago); one that ended does not wait."""
    events = synth_events(100, 2, 25.0, T0, seed=5)
    live, _ = write_run(store, events)  # stored at 1 ns
    waited, _ = write_run(store, events)
    database = open_database(store)
    try:
        for run in (live, waited):
            execute(database, "UPDATE runs SET ended_ns = NULL, last_seen_ns = %s WHERE id = %s", (time.time_ns(), run))
        assert compact(database, 10, min_events=len(events) + 1, waited_ns=1).segments == 0  # at 1: not before 1
        execute(database, "UPDATE batches SET received_ns = 0 WHERE run = %s", (waited,))
        assert compact(database, 10, min_events=len(events) + 1, waited_ns=1).segments == 1  # few, but waited
        assert compact(database, 10, min_events=len(events)).segments == 1  # enough
        quiet, _ = write_run(store, events)
        assert compact(database, 10, min_events=len(events) + 1).segments == 1  # ended: compacted whole
        young, _ = write_run(store, events, received_ns=time.time_ns())
        assert compact(database, time.time_ns() - 60 * 10**9, min_events=1).segments == 0  # not due yet
    finally:
        database.close()
    assert {r for r, in open_database(store)._rows("SELECT run FROM segments")} == {live, waited, quiet}


def test_retention_deletes_segments_and_migrate_copies_them(tmp_path, pg_url):
    path = str(tmp_path / "r.db")
    events = synth_events(100, 2, 25.0, T0, seed=6)
    run, _ = write_run(path, events, skip=(3,))
    database = open_database(path)
    compact(database, time.time_ns(), min_events=1)
    database.close()
    assert table_rows(path, "segments") == 2
    # A run retention deleted, its rollups kept.
    gone, _ = write_run(path, synth_events(100, 2, 25.0, T0 + 10**12, seed=7))
    database = open_database(path)
    compact(database, time.time_ns(), min_events=1)
    session = database._rows("SELECT session FROM runs WHERE id = ?", (gone,))[0][0]
    while database.delete_session_part(session, 100):
        pass
    kept = int(database._rows("SELECT count(*) FROM rollups WHERE run = ?", (gone,))[0][0])
    database.close()
    assert kept > 0 and table_rows(path, "segments") == 2
    result = run_cli("db", "migrate", path, pg_url)
    assert result.returncode == 0, result.stderr
    assert "0 batches, 2 segments" in result.stdout and f"{kept} rollup rows of runs deleted" in result.stdout, result.stdout
    assert np.array_equal(load_runs(path, run)[0].events, load_runs(pg_url, run)[0].events)
    assert table_rows(pg_url, "rollups") == table_rows(path, "rollups")
    assert "0 rollup rows" in run_cli("db", "migrate", path, pg_url).stdout
    for where in (path, pg_url):
        database = open_database(where)
        try:
            session = list_sessions(where)[0]["session"]
            while database.delete_session_part(session, 1):
                pass
        finally:
            database.close()
        assert table_rows(where, "segments") == 0 and list_sessions(where) == []


def test_db_compact_compacts_on_request_and_says_what_it_did(tmp_path):
    path = str(tmp_path / "r.db")
    events = synth_events(100, 2, 25.0, T0, seed=8)
    run, parts = write_run(path, events)
    before = load_runs(path, run)[0].events
    result = run_cli("db", "compact", path)
    assert result.returncode == 0, result.stderr
    assert f"compacted {len(parts)} batches ({len(events)} events) into 1 segments" in result.stdout, result.stdout
    assert np.array_equal(load_runs(path, run)[0].events, before)
    again = run_cli("db", "compact", path)
    assert "compacted 0 batches" in again.stdout
    missing = run_cli("db", "compact", str(tmp_path / "none.db"))
    assert missing.returncode != 0 and "no such relay database" in missing.stderr


@pytest.mark.long
def test_a_relay_killed_mid_compaction_loses_nothing_and_stores_nothing_twice(store, tmp_path):
    """Many runs due at once: the relay's compaction process compacts them from its start (one range
    each, the encoding taking a moment); it is killed (SIGKILL) while some are compacted and others
    not, with its relay, four times, and every run reads back exactly as written after every kill."""
    written, seqs = {}, {}
    for k in range(12):
        events = synth_events(1000, 2, 180.0, T0 + k, seed=k)  # 24,000 events, 120 batches each
        skip = (50,) if k % 5 == 0 else ()
        run, _ = write_run(store, events, skip=skip)
        written[run] = load_runs(store, run, corrected=False)[0].events
        seqs[run] = set(range(120)) - set(skip)
    total_rows = table_rows(store, "batches")
    kills_mid = 0
    for attempt in range(4):
        relay = RelayProcess(store, log=tmp_path / f"relay{attempt}.log", args=["--compact-after", "1"])
        try:
            compactor = wait_for(lambda: get_json(relay.url + "/api/health")["compaction"]["pid"], 10)
            wait_for(lambda: table_rows(store, "segments") > kills_mid or table_rows(store, "batches") == 0, 60,
                     interval=0.01, what="compaction to start")
            time.sleep(0.03 * attempt)
            os.kill(compactor, signal.SIGKILL)  # the compaction process, mid-range: its transaction in flight or not
            relay.kill9()
            kills_mid += 0 < table_rows(store, "batches") < total_rows
        finally:
            if relay.alive():
                relay.kill9()
        for run, events in written.items():
            assert np.array_equal(load_runs(store, run, corrected=False)[0].events, events), f"after kill {attempt}"
            assert open_database(store).stored_seqs(run) == seqs[run]
    assert kills_mid >= 3, (kills_mid, table_rows(store, "batches"), total_rows)
    database = open_database(store)
    try:
        compact(database, time.time_ns(), min_events=1)
    finally:
        database.close()
    assert table_rows(store, "batches") == 0
    for run, events in written.items():
        assert np.array_equal(load_runs(store, run, corrected=False)[0].events, events)
    # Each frame in the rollups once, whatever was killed when.
    from dcuscope.model.delays import node_stats
    from dcuscope.relay.store.history import summary

    complete = sum(node_stats(header_for("a", 2), events)["frames"]["complete"] for events in written.values())
    assert summary(store, "a", 0, time.time_ns())["frame"]["count"] == complete


@pytest.mark.long
def test_a_relay_compacts_as_it_goes_the_stored_stats_are_the_nodes_and_its_history_answers(tmp_path):
    from dcuscope.model.delays import node_stats
    from tests.relay.helpers import assert_stats_equal, load_node, sort_events

    db = tmp_path / "r.db"
    relay = RelayProcess(db, args=["--compact-after", "1"])
    try:
        out = tmp_path / "n.npz"
        node = start_node(relay.url, "dcu-1", out, frames=400, fps=100.0, sources=2, paced=True)
        finish_node(node)
        wait_for(lambda: (get_json(relay.url + "/api/health")["compaction"] or {}).get("batches", 0) > 0, 30,
                 what="the relay to compact")
        wait_for(lambda: table_rows(str(db), "batches") == 0, 30, what="every batch compacted")
        health = get_json(relay.url + "/api/health")["compaction"]
        assert health["segments"] >= 1 and health["bytes_after"] * 3 < health["bytes_before"], health
        answer = get_json(relay.url + "/api/history?node=dcu-1&since=1d")
        assert [n["node"] for n in get_json(relay.url + "/api/history/nodes")] == ["dcu-1"]
        for bad in ("", "?node=dcu-1&since=3q", "?node=dcu-1&until_ns=99999999999999999999999"):
            assert http_status(relay.url + "/api/history" + bad) == 400
    finally:
        relay.stop()
    header, events = load_node(out)
    exact = node_stats(header, events)
    assert answer["summary"]["frame"]["count"] == exact["frames"]["complete"]
    assert {k: v["count"] for k, v in answer["summary"]["stages"].items()} == {k: v["count"] for k, v in exact["stages"].items()}
    assert sum(p["frames"] for p in answer["history"]["frame"]) == exact["frames"]["complete"]
    (stored,) = load_runs(db, list_sessions(db)[0]["session"], corrected=False)
    assert np.array_equal(sort_events(stored.events), sort_events(events))
    assert_stats_equal(node_stats(header, events), node_stats(stored.header, stored.events))


def test_a_store_of_the_layout_before_is_read_brought_to_schema_5_and_compacted(store):
    """A store as a relay before compaction left it (schema 4: batches only): opened, it gains the
    tables it lacks, reads as before, and compacts."""
    events = synth_events(100, 2, 25.0, T0, seed=9)
    run, _ = write_run(store, events)
    database = open_database(store)
    for sql in ("DROP TABLE segments", "DROP TABLE rollups", "ALTER TABLE runs DROP COLUMN rolled_lost",
                "UPDATE meta SET value = '4' WHERE key = 'schema'"):
        execute(database, sql)
    database.close()
    assert np.array_equal(load_runs(store, run, corrected=False)[0].events, events)
    database = open_database(store)
    try:
        assert database._rows("SELECT value FROM meta WHERE key = 'schema'") == [("5",)]
        assert compact(database, time.time_ns(), min_events=1).events == len(events)
    finally:
        database.close()
    assert np.array_equal(load_runs(store, run, corrected=False)[0].events, events)
    assert table_rows(store, "rollups") > 0
