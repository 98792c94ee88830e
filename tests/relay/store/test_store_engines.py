"""The relay's store, the same tests against each engine: SQLite (a file) and PostgreSQL (a real
server, tests/pgserver.py): group commits, deduplication, sessions, owners, clock history,
reading back, retention."""

from __future__ import annotations

import asyncio
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import psycopg
import pytest

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.events import CAPTURE, ORIGIN
from dcuscope.protocol.wire import encode_batch
from dcuscope.relay.clock.correction import Segment
from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.base import BatchRow, NotOwner
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.postgres import PostgresDatabase
from dcuscope.relay.store.runs import frame_starts, list_sessions, load_runs, load_session
from dcuscope.relay.store.writer import Storage
from tests.relay.helpers import wait_for

T0 = 1_700_000_000_000_000_000
SHORT_LEASE_S = 1.0
"""The lease tests' (a relay's is relay.store.base.LEASE_S, 4 s): what they show does not depend on it."""


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request, tmp_path) -> str:
    """Where a store is: an SQLite file, or an empty PostgreSQL database."""
    if request.param == "sqlite":
        return str(tmp_path / "r.db")
    return request.getfixturevalue("pg_url")


def payload(run: str, seq: int, events: np.ndarray, compress: bool) -> bytes:
    return encode_batch(run, seq, events, compress)[40:]


def execute(database, sql: str, args: tuple = ()) -> None:
    """A statement written by hand (what no relay would write), in either engine's placeholders."""
    if database.engine == "sqlite":
        database.conn.execute(sql.replace("%s", "?"), args)
    else:
        database.conn.execute(sql, args)


def stored_run(store: str, events: np.ndarray, clock: dict, history: list[Segment] = (), run: str | None = None) -> str:
    """One run of node "a" stored as a relay stores it: owned, registered, one batch, its clock."""
    run = run or uuid.uuid4().hex
    database = open_database(store)
    try:
        assert database.own_run(run)
        database.register_run(run, "a", header_for("a", 1).to_dict(), None, None)
        assert database.put_batches([BatchRow(run, 0, len(events), False, payload(run, 0, events, False))],
                                    time.time_ns()) == [True]
        database.update_run(run, clock=clock, history=[s.to_dict() for s in history])
        # Given back as a relay does when its node leaves: a closed connection's locks go only
        # once its server process has ended, a moment after the client closed it.
        database.disown_run(run)
    finally:
        database.close()
    return run


def test_batches_sessions_and_reload(store):
    h1, h2 = header_for("a", 2), header_for("b", 1)
    ev1 = synth_events(30, 2, 25.0, T0, seed=1)
    ev2 = synth_events(30, 1, 25.0, T0, seed=2)
    r1, r2, r3 = (uuid.uuid4().hex for _ in range(3))

    async def scenario():
        s = Storage(store)
        s.start(asyncio.get_running_loop())
        assert await s.call("own_run", r1) and await s.call("own_run", r2)
        s1, first, secret = await s.call("register_run", r1, "a", h1.to_dict(), None, None)
        s2, _, _ = await s.call("register_run", r2, "b", h2.to_dict(), s1, None)  # joins the live session
        # A renewed hello, with the secret issued at the first
        assert await s.call("register_run", r1, "a", h1.to_dict(), None, secret) == (1, first, None)
        assert s1 == s2 == 1
        halves = np.array_split(ev1, 3)
        results = await asyncio.gather(*(s.put_batch(r1, i, len(p), i == 1, payload(r1, i, p, i == 1))
                                         for i, p in enumerate(halves)))
        assert results == [True, True, True]
        assert await s.put_batch(r1, 1, len(halves[1]), True, payload(r1, 1, halves[1], True)) is False  # resent
        assert await s.put_batch(r2, 0, len(ev2), False, payload(r2, 0, ev2, False))
        await s.call("update_run", r2, clock={"correction_ns": 1000}, ended_ns=5, dropped=2, lost=1)
        assert await s.call("stored_seqs", r1) == {0, 1, 2}
        with pytest.raises(RelayError, match="belongs to node 'a'"):
            await s.call("register_run", r1, "b", h1.to_dict(), None, secret)
        with pytest.raises(RelayError, match="takes the secret issued at its first hello"):
            await s.call("register_run", r1, "a", h1.to_dict(), None, "not the secret")
        await s.call("disown_run", r1)  # its node left: nothing is live now
        assert await s.call("own_run", r3)
        s3, _, _ = await s.call("register_run", r3, "a", h1.to_dict(), None, None)  # a new session
        assert s3 == 2
        assert s.commits >= 2 and s.health()["ok"] and s.health()["engine"] == ("postgresql" if store.startswith("postgresql") else "sqlite")
        s.stop()

    asyncio.run(scenario())

    runs = load_runs(store, 1)
    assert [r.header.node for r in runs] == ["a", "b"]
    assert np.array_equal(runs[0].events, ev1)
    shifted = ev2.copy()
    shifted["ts"] -= 1000
    assert np.array_equal(runs[1].events, shifted) and runs[1].dropped == 2 and runs[1].ended
    assert np.array_equal(load_runs(store, 1, corrected=False)[1].events, ev2)
    (h, e), = load_session(store, r1[:8])
    assert h.node == "a" and len(e) == len(ev1)
    sessions = list_sessions(store)
    assert [s["session"] for s in sessions] == [2, 1]
    assert [r["events"] for r in sessions[1]["runs"]] == [len(ev1), len(ev2)]
    with pytest.raises(RelayError, match="no session or run"):
        load_session(store, 3)
    with pytest.raises(RelayError, match="must be a number or a run id"):
        load_session(store, "x; DROP TABLE runs")


def test_a_batch_the_store_cannot_bind_fails_alone_and_the_writer_keeps_serving(store):
    """A value the engine refuses (a seq beyond 64 bits) used to kill the writer thread, and every
    later put_batch waited for ever."""
    run = uuid.uuid4().hex
    events = synth_events(5, 1, 25.0, T0)

    async def scenario():
        s = Storage(store)
        s.start(asyncio.get_running_loop())
        try:
            assert await s.call("own_run", run)
            await s.call("register_run", run, "a", header_for("a", 1).to_dict(), None, None)
            with pytest.raises(RelayError, match="cannot store batches"):
                await asyncio.wait_for(s.put_batch(run, 1 << 64, len(events), False, payload(run, 0, events, False)), 10)
            stored = await asyncio.wait_for(s.put_batch(run, 0, len(events), False, payload(run, 0, events, False)), 10)
            assert stored is True and await s.call("stored_seqs", run) == {0}
        finally:
            s.stop()
        with pytest.raises(RelayError, match="storage is not running"):
            await s.put_batch(run, 1, len(events), False, payload(run, 1, events, False))

    asyncio.run(scenario())


def test_a_stored_history_corrects_each_timestamp_and_a_poisoned_one_falls_back(store, caplog):
    events = synth_events(50, 1, 25.0, T0)  # two seconds of frames
    half = int(T0) + 1_000_000_000
    history = [Segment(int(T0) - 10**9, int(T0), 5000, 0, 100), Segment(half, half, 9000, 1000, 50, 200)]
    run = stored_run(store, events, {"applied": "estimate", "correction_ns": 9000}, history)
    database = open_database(store)
    assert database.own_run(run)  # a run's fields are written by its owner (its lease, on a shared store)
    database.update_run(run, history=[s.to_dict() for s in history], ended_ns=5)  # written again: the same rows
    assert database.run_history(run) == history
    (stored,) = load_runs(store, run[:8])
    starts = frame_starts(events)
    expected = np.where(starts < half, 5000, 9000 + (events["ts"] - half) // 1_000_000)
    assert np.abs(stored.events["ts"] - (events["ts"] - expected)).max() <= 1
    assert (starts < half).sum() > 100 and (starts >= half).sum() > 100  # both segments in use
    assert stored.correction.uncertainties(np.array([half + 10**9]))[0] == 50 + 200
    # A row no relay could have written: the run's last estimate instead, with one warning.
    execute(database, "UPDATE clock_history SET drift_ppb = %s WHERE from_ns = %s", (10**12, half))
    database.close()
    (stored,) = load_runs(store, run[:8])
    assert np.array_equal(stored.events["ts"], events["ts"] - 9000)
    assert [r.message for r in caplog.records if "history" in r.message] == [
        f"run {run}: stored clock history: drift 1000000000000 beyond 1000000; its last estimate is applied instead"]


def test_frame_starts_are_each_frames_earliest_time_in_any_order():
    events = synth_events(30, 3, 25.0, T0, seed=4)
    events = events[np.random.default_rng(0).permutation(len(events))]
    first: dict = {}
    for s, f, t in zip(events["source"].tolist(), events["frame"].tolist(), events["ts"].tolist()):
        first[(s, f)] = min(t, first.get((s, f), t))
    assert frame_starts(events).tolist() == [first[(s, f)] for s, f in zip(events["source"].tolist(),
                                                                            events["frame"].tolist())]


def test_capture_times_are_the_cameras_clock_and_stay_as_stored(store):
    """A node's correction moves its own timestamps, never a frame's capture time (the camera's
    clock, from RTCP sender reports), nor does the capture, the earliest time of a frame, pick
    the estimate the frame is corrected by."""
    events = synth_events(50, 1, 25.0, T0)
    origins = events[events["point"] == ORIGIN]
    captures = origins.copy()
    captures["point"], captures["stage"] = CAPTURE, 0
    captures["ts"] -= 2 * 10**9  # two seconds earlier: before the second segment's start
    events = np.concatenate([events, captures])
    half = int(T0) + 1_000_000_000
    history = [Segment(int(T0) - 10**9, int(T0), 5000, 0, 100), Segment(half, half, 9000, 0, 50)]
    run = stored_run(store, events, {"applied": "estimate", "correction_ns": 9000}, history)
    (stored,) = load_runs(store, run[:8])
    assert np.array_equal(stored.events[["source", "frame", "point"]], events[["source", "frame", "point"]])
    is_capture = events["point"] == CAPTURE
    assert np.array_equal(stored.events["ts"][is_capture], captures["ts"])
    moved = events["ts"] - stored.events["ts"]
    starts = frame_starts(events, ~is_capture)
    # Each frame by the segment of its own start, not of its capture (all before the second).
    assert np.array_equal(moved[~is_capture], np.where(starts < half, 5000, 9000)[~is_capture])
    assert set(moved[~is_capture].tolist()) == {5000, 9000}


def test_a_run_id_whose_prefix_is_all_digits_is_found_by_it(store):
    """1 run id in 43 begins with 8 decimal digits: its prefix read as a session number found
    nothing ("no session or run '12812422'", which failed a test at random)."""
    events = synth_events(5, 1, 25.0, T0)
    run = stored_run(store, events, {"applied": "none", "correction_ns": 0}, run="12812422" + uuid.uuid4().hex[8:])
    (stored,) = load_runs(store, run[:8])
    assert stored.run == run and np.array_equal(stored.events, events)
    assert [r.run for r in load_runs(store, 1)] == [run]  # a session number is still one
    with pytest.raises(RelayError, match="no session or run '999999'"):
        load_runs(store, "999999")


def test_old_sessions_are_deleted_in_bounded_parts_and_live_ones_kept(store):
    events = synth_events(5, 1, 25.0, T0)
    old = stored_run(store, events, {})
    database = open_database(store)
    try:
        if database.shared:  # this connection does not own it
            with pytest.raises(NotOwner):
                database.put_batches([BatchRow(old, 1, len(events), False, payload(old, 1, events, False))], 1)
        assert database.own_run(old)
        assert database.put_batches([BatchRow(old, i, len(events), False, payload(old, i, events, False))
                                     for i in range(1, 5)], 1) == [True] * 4
        database.disown_run(old)
        live = uuid.uuid4().hex
        assert database.own_run(live)
        database.register_run(live, "b", header_for("b", 1).to_dict(), None, None)
        execute(database, "UPDATE runs SET last_seen_ns = 1")  # both as if last heard from long ago
        expired = database.expired_sessions(before_ns=2)
        # On a shared store a run some relay owns is live, whenever it was last heard from.
        assert expired == ([1] if database.shared else [1, 2])
        parts = []
        while (n := database.delete_session_part(1, limit=2)):
            parts.append(n)
        # five batches two at a time, then its run and session (and on a shared store its lease)
        assert parts == [2, 2, 1, 3 if database.shared else 2]
        assert [s["session"] for s in database.list_sessions()] == [2]
    finally:
        database.close()


def test_a_store_that_cannot_be_reached_says_where(pg_url, tmp_path):
    unreachable = pg_url.rsplit(":", 1)[0] + ":1/none"
    with pytest.raises(RelayError, match="cannot connect"):
        open_database(unreachable)
    with pytest.raises(RelayError, match="no such relay database"):
        load_runs(tmp_path / "missing.db", 1)


def test_an_sqlite_file_is_migrated_into_postgresql_whole_and_once(tmp_path, pg_url):
    from tests.conftest import run_cli

    path = str(tmp_path / "r.db")
    events = synth_events(20, 1, 25.0, T0)
    history = [Segment(int(T0) - 10**9, int(T0), 5000, 0, 100)]
    runs = [stored_run(path, events, {"applied": "estimate", "correction_ns": 5000}, history) for _ in range(2)]
    database = open_database(path)
    database.mark_rejected(runs[1], "a test's")
    database.close()
    result = run_cli("db", "migrate", path, pg_url)
    assert result.returncode == 0, result.stderr
    assert "copied 2 sessions, 2 runs, 2 batches" in result.stdout, result.stdout  # a session each
    assert list_sessions(pg_url) == list_sessions(path)  # the refused run left out on both
    (a,), (b,) = load_runs(path, runs[0]), load_runs(pg_url, runs[0])
    assert np.array_equal(a.events, b.events) and a.correction == b.correction and a.clock == b.clock
    again = run_cli("db", "migrate", path, pg_url)
    assert "copied 0 sessions, 0 runs, 0 batches" in again.stdout and "2 runs already there" in again.stdout
    bad = run_cli("db", "migrate", str(tmp_path / "none.db"), pg_url)
    assert bad.returncode != 0 and "no such relay database" in bad.stderr


def test_retention_deletes_the_sessions_older_than_its_days_through_the_writer(store):
    from dcuscope.relay.store.retention import expire

    events = synth_events(5, 1, 25.0, T0)
    old, new = stored_run(store, events, {}), stored_run(store, events, {})
    database = open_database(store)
    execute(database, "UPDATE runs SET last_seen_ns = %s WHERE id = %s", (1, old))  # heard from in 1970
    database.close()

    async def scenario():
        s = Storage(store)
        s.start(asyncio.get_running_loop())
        try:
            return await expire(s, days=30)
        finally:
            s.stop()

    assert asyncio.run(scenario()) == [1]
    assert [r["run"] for s in list_sessions(store) for r in s["runs"]] == [new]


def test_a_relay_connecting_does_not_wait_on_another_relays_open_write(pg_url):
    """A new connection (a relay starting, a session reader) finds the schema there and takes no
    lock on its tables: before, its DDL waited on a write in progress (and, with that write then
    waiting on it, deadlocked: the writing relay thought its store lost and let its nodes go)."""
    first = open_database(pg_url)
    run = uuid.uuid4().hex
    assert first.own_run(run)
    first.register_run(run, "a", header_for("a", 1).to_dict(), None, None)
    writer = psycopg.connect(pg_url)  # a transaction left open holding a write on batches and runs
    try:
        writer.execute("INSERT INTO batches VALUES (%s, 0, 1, false, 0, '\\x00')", (run,))
        writer.execute("UPDATE runs SET events = 1 WHERE id = %s", (run,))
        # Waiting for a lock more than 5 s fails the connection's schema step (it waited for ever before).
        waits = "&" if "?" in pg_url else "?"
        open_database(f"{pg_url}{waits}options=-c%20lock_timeout%3D5000").close()
    finally:
        writer.rollback()
        writer.close()
        first.close()


def test_a_transaction_postgresql_rolls_back_as_a_deadlock_is_tried_again(pg_url):
    """Two writers locking two runs in opposite orders: PostgreSQL breaks the deadlock by rolling
    one back; when that one is the relay's, the relay tries it again and it commits."""
    database = open_database(pg_url)
    a, b = uuid.uuid4().hex, uuid.uuid4().hex
    for run in (a, b):
        database.register_run(run, "a", header_for("a", 1).to_dict(), None, None)
    # Each waiter checks for a deadlock once, deadlock_timeout after it began to wait: the relay's side
    # waits first and checks after 3 s, by when the other waits too (a loaded machine once took over
    # PostgreSQL's default 1 s to get there, and the other's own check then picked the other).
    other = psycopg.connect(pg_url, options="-c deadlock_timeout=20s")
    locked_b, locked_a = threading.Event(), threading.Event()
    tries = []

    def relay_side(cur) -> None:  # b then a; it checks first, so PostgreSQL's check picks it as the victim
        tries.append(1)
        cur.execute("SET LOCAL deadlock_timeout = '3s'")
        cur.execute("UPDATE runs SET events = events + 1 WHERE id = %s", (b,))
        if len(tries) == 1:
            locked_b.set()
            locked_a.wait(10)
        cur.execute("UPDATE runs SET events = events + 1 WHERE id = %s", (a,))

    try:
        with ThreadPoolExecutor(1) as pool:
            done = pool.submit(database._transaction, relay_side)
            assert locked_b.wait(10)
            other.execute("UPDATE runs SET events = events + 10 WHERE id = %s", (a,))
            locked_a.set()
            with psycopg.connect(pg_url, autocommit=True) as monitor:  # the relay's side waits on a first
                assert wait_for(lambda: monitor.execute(
                    "SELECT 1 FROM pg_stat_activity WHERE datname = current_database() AND wait_event_type = 'Lock'"
                ).fetchone(), 10, 0.02, "the relay's side waiting on a")
            other.execute("UPDATE runs SET events = events + 10 WHERE id = %s", (b,))
            other.commit()
            done.result(timeout=30)
        # Rolled back, then committed on a later try: on a loaded machine its second try has once met the
        # other in a second deadlock (3 tries, CI), which it also survived.
        assert len(tries) >= 2 and database.conflicts == len(tries) - 1, (tries, database.conflicts)
        events = dict(other.execute("SELECT id, events FROM runs WHERE id IN (%s, %s)", (a, b)).fetchall())
        assert events == {a: 11, b: 11}
    finally:
        other.close()
        database.close()


def test_a_relay_whose_lease_was_taken_is_refused_by_the_store_fenced_by_its_generation(pg_url):
    """Relay X owns a run, then stops renewing (frozen): after LEASE_S relay Y may take it, though X's
    connection, and its advisory lock, are still there. X, awake, tries to write a batch it had
    received and the run's end: the store refuses both in their transactions (the generation X took
    is not the lease's any more), writes nothing, and X's next renewal says the run was taken."""
    x, y = PostgresDatabase(pg_url, "x", lease_s=SHORT_LEASE_S), PostgresDatabase(pg_url, "y", lease_s=SHORT_LEASE_S)
    run = uuid.uuid4().hex
    events = synth_events(5, 1, 25.0, T0)
    try:
        assert x.own_run(run)
        x.register_run(run, "a", header_for("a", 1).to_dict(), None, None)
        assert x.put_batches([BatchRow(run, 0, len(events), False, payload(run, 0, events, False))], 1) == [True]
        assert not y.own_run(run)  # held, and X's connection holds its advisory lock: no fast path
        time.sleep(SHORT_LEASE_S + 0.2)  # X renews nothing meanwhile
        assert y.own_run(run)  # expired: taken, generation 2
        with pytest.raises(NotOwner):
            x.put_batches([BatchRow(run, 1, len(events), False, payload(run, 1, events, False))], 1)
        with pytest.raises(NotOwner):
            x.update_run(run, ended_ns=5, written=10)
        assert x.renew() == set() and run not in x.owned  # the refusal already told X
        assert y.put_batches([BatchRow(run, 1, len(events), False, payload(run, 1, events, False))], 1) == [True]
        assert y.renew() == set()
        (stored,) = [r for s in list_sessions(pg_url) for r in s["runs"] if r["run"] == run]
        assert stored["events"] == 2 * len(events) and stored["ended_ns"] is None  # X's write: none of it
        assert y.stored_seqs(run) == {0, 1}
        # A relay killed (its connection ends, its advisory locks with it) lets its runs go at once,
        # without the wait for their leases: the fast path.
        other, z = uuid.uuid4().hex, PostgresDatabase(pg_url, "z")  # z: a relay's lease, 4 s
        assert z.own_run(other) and not x.own_run(other)
        z.close()
        wait_for(lambda: not y._rows("SELECT 1 FROM pg_stat_activity WHERE application_name = 'dcuscope-relay z'"),
                 3, 0.02, what="z's session ended")
        assert x.own_run(other)  # well before z's lease expires
    finally:
        x.close()
        y.close()


def test_a_group_with_one_fenced_run_stores_nothing_and_a_batch_twice_in_a_group_counts_once(pg_url):
    """PostgreSQL stores a group of batches in one statement (the fence, the rows, the counts): a
    run of the group whose lease was taken stores nothing of the group, and names only that run;
    the rest, sent again alone, is stored. A batch queued twice in a group is stored and counted once."""
    x, y = PostgresDatabase(pg_url, "x", lease_s=SHORT_LEASE_S), PostgresDatabase(pg_url, "y", lease_s=SHORT_LEASE_S)
    kept, taken = uuid.uuid4().hex, uuid.uuid4().hex
    events = synth_events(5, 1, 25.0, T0)

    def batch(run: str, seq: int) -> BatchRow:
        return BatchRow(run, seq, len(events), False, payload(run, seq, events, False))

    def counted(run: str) -> int:
        return next(r["events"] for s in list_sessions(pg_url) for r in s["runs"] if r["run"] == run)

    try:
        for run in (kept, taken):
            assert x.own_run(run)
            x.register_run(run, "a" if run == kept else "b", header_for("a", 1).to_dict(), None, None)
        time.sleep(SHORT_LEASE_S + 0.2)  # X renews nothing meanwhile: Y takes one of the two
        assert y.own_run(taken)
        with pytest.raises(NotOwner) as refused:
            x.put_batches([batch(kept, 0), batch(taken, 0)], 1)
        assert refused.value.runs == {taken} and taken not in x.owned and kept in x.owned
        assert x.stored_seqs(kept) == set() and counted(kept) == 0
        assert x.renew() == set()  # the kept lease renewed (it had expired, but nobody took it)
        assert x.put_batches([batch(kept, 0), batch(kept, 1), batch(kept, 0)], 1) == [True, True, False]
        assert x.stored_seqs(kept) == {0, 1} and counted(kept) == 2 * len(events)
        assert x.put_batches([batch(kept, 1)], 1) == [False] and counted(kept) == 2 * len(events)
    finally:
        x.close()
        y.close()


def test_a_lease_not_renewed_is_lost_at_the_next_renewal(pg_url):
    x, y = PostgresDatabase(pg_url, "x", lease_s=SHORT_LEASE_S), PostgresDatabase(pg_url, "y", lease_s=SHORT_LEASE_S)
    run = uuid.uuid4().hex
    try:
        assert x.own_run(run)
        assert x.renew() == set()
        time.sleep(SHORT_LEASE_S + 0.2)
        assert y.own_run(run)
        assert x.renew() == {run} and not x.owned
    finally:
        x.close()
        y.close()


def test_a_writer_plans_its_group_statement_once_and_stores_what_it_is_given(pg_url):
    """A relay's writer (``writer=True``) plans the statement that stores a group once per session:
    PostgreSQL, left to choose, plans it again at every execution (counted in its own
    pg_prepared_statements, as another connection shows). Its payloads, sent in binary, come back
    byte for byte."""
    events = synth_events(5, 1, 25.0, T0)
    plans = {}
    for writer in (True, False):
        database = open_database(pg_url, name="w" if writer else "r", writer=writer)
        run = uuid.uuid4().hex
        try:
            assert database.own_run(run)
            database.register_run(run, "n", header_for("n", 1).to_dict(), None, None)
            sent = {seq: payload(run, seq, events, seq % 2 == 0) for seq in range(12)}
            for seq, data in sent.items():
                assert database.put_batches([BatchRow(run, seq, len(events), seq % 2 == 0, data)], 1) == [True]
            plans[writer] = database.conn.execute(
                "SELECT generic_plans, custom_plans FROM pg_prepared_statements WHERE statement LIKE %s",
                ("%INSERT INTO batches%",)).fetchone()
            stored = dict(database.conn.execute("SELECT seq, data FROM batches WHERE run = %s", (run,)).fetchall())
            assert {seq: bytes(data) for seq, data in stored.items()} == sent
        finally:
            database.close()
    assert plans[True][1] == 0 and plans[True][0] >= 1, plans
    assert plans[False][1] > 1, plans
